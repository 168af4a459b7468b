"""What encoding a trace costs per component and row: the Python encoder, the C encoder, zstd levels
(encoding is most of what tracing every step costs).

    python -m benchmarks.trace_encoder                   # paper platoon, N = 16, 10 000 rows, 5 rounds
    python -m benchmarks.trace_encoder --vehicles 64 --steps 2000 --rounds 3

One native-engine run of the paper platoon (untimed) gives the rows; the same rows then go, in this
process, rounds interleaved, through:

* ``python``: ``TraceWriter(native=False).write_block`` (orchestrator/trace/encoding.py, foxglove.py): the
  reference, what the Python engine's runs use;
* ``native``: ``TraceWriter(native=True).write_block`` (orchestrator/trace/native_encoder.c): what the
  native engine's runs use;
* ``native-encode``: the C encoder alone, no chunk, no compression, no file;

every channel (components, errors, scene and transforms at 10 Hz), chunks closed as in a run, the
file finalized. CPU seconds (``time.process_time``) per component and row, medians; and the
compression of the native file's chunks at zstd levels 3 (the ``mcap`` library's default), 1 (what the
writer uses), -1 and lz4: MB/s and the compressed size. Prints a table; writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from fmus.builders import DEFAULT_OUT

from .common import PAPER_CONFIGS, markdown_table

PAPER = PAPER_CONFIGS / "platoon.toml"
VARIANTS = ("python", "native", "native-encode")


def run_rows(vehicles: int, steps: int, folder: Path, fmu_dir: Path) -> tuple[Any, list, np.ndarray]:
    """(config, components, rows) of one native-engine run of the paper platoon, read back from its trace."""
    from orchestrator.scenario.config import load_config
    from orchestrator.execution.run import run_scenario
    from orchestrator.trace import load

    config, _ = load_config(PAPER, [f"platoon.count={vehicles}", f"simulation.stop_time={steps * 0.01!r}",
                                    "simulation.fmus=native"])
    result = run_scenario(config, PAPER.read_text(), folder / "rows.mcap", engine="native", fmu_dir=fmu_dir)
    trace = load(result.trace)
    names = ["target", *(f"vehicle{k}" for k in range(1, vehicles + 1))]
    columns = {name: trace.component(name) for name in names}
    components = [(name, [key for key in columns[name] if key != "t"]) for name in names]
    rows = np.column_stack([columns["target"]["t"]] + [columns[name][key] for name, keys in components for key in keys])
    return config, components, rows


def time_variant(variant: str, config: Any, components: list, rows: np.ndarray, path: Path) -> float:
    """CPU seconds to encode ``rows`` (blocks of 500, as the native engine delivers them)."""
    from orchestrator.trace import TraceWriter
    from orchestrator.trace.encoding import ComponentMessages
    from orchestrator.trace.foxglove import FoxgloveChannels
    from orchestrator.trace.native_rows import native_encoder

    foxglove = FoxgloveChannels(config, components)
    started = time.process_time()
    if variant == "native-encode":
        foxglove.channels = {"errors": 1000, "tf": 1001, "scene": 1002, "log": 1003}
        encoder = native_encoder(ComponentMessages(components), list(range(1, len(components) + 1)), foxglove)
        for start in range(0, len(rows), 500):
            block, row = rows[start:start + 500], 0
            while row < len(block):  # a call stops at the chunk size: the writer would close the chunk there
                row = encoder.encode(block, row, 0, 1 << 20, start + row)[0]
    else:
        writer = TraceWriter(path, components, foxglove=foxglove, native=variant == "native")
        for start in range(0, len(rows), 500):
            writer.write_block(rows[start:start + 500])
        writer.close()
    return time.process_time() - started


def compression(path: Path) -> list[list[Any]]:
    """zstd levels and lz4 on the chunks of ``path``: [name, MB/s, compressed MB] rows."""
    import lz4.frame
    import zstandard
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as stream:
        chunks = [zstandard.ZstdDecompressor().decompress(r.data, max_output_size=r.uncompressed_size)
                  for r in StreamReader(stream, skip_magic=False, emit_chunks=True).records if isinstance(r, Chunk)]
    size = sum(len(c) for c in chunks)
    rows: list[list[Any]] = [["uncompressed", "", f"{size / 1e6:.1f}"]]
    for name, compress in (("zstd 3", zstandard.ZstdCompressor(level=3).compress),
                           ("zstd 1", zstandard.ZstdCompressor(level=1).compress),
                           ("zstd -1", zstandard.ZstdCompressor(level=-1).compress), ("lz4", lz4.frame.compress)):
        started = time.process_time()
        out = sum(len(compress(chunk)) for chunk in chunks)
        rows.append([name, f"{size / (time.process_time() - started) / 1e6:.0f}", f"{out / 1e6:.1f}"])
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.trace_encoder", description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", type=int, default=16)
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-trace-encoder-") as scratch:
        folder = Path(scratch)
        config, components, rows = run_rows(args.vehicles, args.steps, folder, DEFAULT_OUT)
        samples: dict[str, list[float]] = {v: [] for v in VARIANTS}
        for round_ in range(args.rounds):
            for variant in VARIANTS[round_ % 3:] + VARIANTS[:round_ % 3]:
                samples[variant].append(time_variant(variant, config, components, rows, folder / f"{variant}.mcap"))
        per = len(rows) * len(components)
        table = [[v, f"{statistics.median(samples[v]):.3f}", f"{statistics.median(samples[v]) / per * 1e6:.2f}"]
                 for v in VARIANTS]
        print(f"N = {args.vehicles}, {len(rows)} rows, {len(components)} components, every channel; "
              f"CPU time, median of {args.rounds} interleaved rounds\n")
        print(markdown_table(["encoder", "s", "µs per component and row"], table))
        print(f"\nratio python / native: {statistics.median(samples['python']) / statistics.median(samples['native']):.2f}\n")
        print(markdown_table(["chunk compression", "MB/s (CPU)", "MB"], compression(folder / "native.mcap")))


if __name__ == "__main__":
    main()
