"""Campaigns: parameter sweeps over a base config that resume, on local worker processes or on Dask.

A sweep file (docs/sweeps.md) names a base config, fixed overrides (``[set]``), a grid (every
combination) and random samples (``[random]``). The pieces, one job each:

* ``spec.py``: reads and checks the sweep file (errors name the file and the key);
* ``plan.py``: the runs, each a set of ``--set`` overrides with a stable id (a hash of its values), and
  the validated config each run gets;
* ``worker.py``: one run in a process of its own, forked from a warm worker (``python -m
  orchestrator.sweep.worker``, the sweep's side in ``warm.py``): run_scenario, then the summary
  ``platoon report --json`` prints, flattened into a row;
* ``executors.py``: where the runs execute: local worker processes, or a Dask distributed cluster;
* ``store.py``: the output folder: one result file per finished run (written atomically), traces,
  ``results.csv`` (and ``results.parquet``) rebuilt from them, and the lock against a second sweep;
* ``runner.py``: the loop that submits what is not done yet and records each run as it finishes;
* ``plot.py``: the maps of ``platoon sweep-plot`` (the commands themselves: orchestrator/cli/sweep.py).
"""
