/*
 * loader.h - what minimal_host.c and minimal_host3.c need from the operating system: load a shared
 * library, find a function in it, say why not, and the folder below binaries/ that holds this
 * platform's binary (FMI 2.0: linux64, win64, darwin64; FMI 3.0: the platform tuple, e.g.
 * aarch64-linux). POSIX dlopen()/dlsym(), or the Windows API when compiled for Windows, so the same
 * hosts run the FMUs' cross-compiled binaries (under qemu-user and wine in tests/test_platforms.py).
 */
#ifndef PLATOON_LOADER_H
#define PLATOON_LOADER_H

#include <stdio.h>

#if defined(_WIN32)
#include <windows.h>
typedef HMODULE library_t;
static inline library_t library_open(const char *path) { return LoadLibraryA(path); }
static inline void *library_symbol(library_t lib, const char *name) { return (void *)GetProcAddress(lib, name); }
static inline void library_close(library_t lib) { FreeLibrary(lib); }
static inline const char *library_error(void)
{
    static char text[48];
    snprintf(text, sizeof text, "Windows error %lu", (unsigned long)GetLastError());
    return text;
}
#define FMU_SUFFIX ".dll"
#define FMI2_PLATFORM "win64"
#define FMI3_SYSTEM "windows"
#else
#include <dlfcn.h>
typedef void *library_t;
static inline library_t library_open(const char *path) { return dlopen(path, RTLD_NOW | RTLD_LOCAL); }
static inline void *library_symbol(library_t lib, const char *name) { return dlsym(lib, name); }
static inline void library_close(library_t lib) { dlclose(lib); }
static inline const char *library_error(void) { return dlerror(); }
#if defined(__APPLE__)
#define FMU_SUFFIX ".dylib"
#define FMI2_PLATFORM "darwin64"
#define FMI3_SYSTEM "darwin"
#else
#define FMU_SUFFIX ".so"
#define FMI2_PLATFORM "linux64"
#define FMI3_SYSTEM "linux"
#endif
#endif

#if defined(__aarch64__) || defined(_M_ARM64)
#define FMI3_ARCHITECTURE "aarch64"
#else
#define FMI3_ARCHITECTURE "x86_64"
#endif
#define FMI3_PLATFORM FMI3_ARCHITECTURE "-" FMI3_SYSTEM

#endif
