"""python tools/scatter_floor.py LAW DELAY LOSS SEEDS (from the checkout; docs/model.md, "One verdict, and a single run's confidence").

Per lossy point of the study (extra --set overrides after SEEDS, e.g. simulation.coupling=hold), SEEDS seeds of real runs (native FMUs): per probe the
headline growth over the clean links, its mean over seeds against the cascade (within 0.3 % + 4 sigma/sqrt(6)),
the seeds' spread against 2.5 sigma, sigma the analysis' predicted scatter of one run."""
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from orchestrator.analysis.error_gains import (clean_order, predicted_gains, predicted_run_scatter, probe_frequencies,
                                               steady_window, vehicle_errors)
from orchestrator.analysis.headline import probe_amplitudes
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import load_config
from orchestrator.trace import load

law, delay, loss, seeds, extra = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5:]
base = [f"platoon.speed_law={law}", f"links.delay={delay}", f"links.loss={loss}", "simulation.trace_every=5", *extra]
growths = []
scratch = tempfile.mkdtemp(prefix="scatter-floor-")  # the traces, kept for `platoon stability`
for seed in range(seeds):
    config, _ = load_config("configs/study/string_stability.toml", base + [f"links.seed={seed}"])
    result = run_scenario(config, "", Path(scratch) / f"{seed}.mcap", foxglove=False)
    trace = load(result.trace)
    names = trace.vehicles()
    clean, probes = clean_order(config, names), probe_frequencies(config)
    window = steady_window(config, config.simulation.stop_time)
    a = probe_amplitudes(vehicle_errors(trace, config), clean, probes, window)
    growths.append((a[-1] / a[0]) ** (1.0 / (len(clean) - 1)))
growths = np.array(growths)
scatter = predicted_run_scatter(config, clean, window)
cascade = [math.prod(row) ** (1.0 / len(row)) for row in predicted_gains(config, names, clean, probes)]
print(f"{law} {delay} s {loss} loss, {seeds} seeds ({' -> '.join(clean)}):")
for k, w in enumerate(probes):
    mean, spread, sigma = growths[:, k].mean(), growths[:, k].std(ddof=1), scatter.sigma[k]
    bound = 0.003 * cascade[k] + 4 * sigma / math.sqrt(seeds)
    print(f"  {w:g} rad/s: cascade {cascade[k]:.4f}, model mean {scatter.growth[k]:.4f}, predicted sigma {sigma:.2g}; "
          f"seeds mean {mean:.4f} (|diff| {abs(mean - cascade[k]):.2g} <= {bound:.2g}: {abs(mean - cascade[k]) <= bound}), "
          f"spread {spread:.2g} (<= 2.5 sigma = {2.5 * sigma:.2g}: {spread <= 2.5 * sigma})  runs "
          + " ".join(f"{g:.4f}" for g in growths[:, k]))
