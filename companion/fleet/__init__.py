"""Fleets and sweeps beyond one machine (issue 15).

- ``engine``: where independent tasks run: a Dask ``LocalCluster``, the cluster at a scheduler's
  address, or this process (Dask is the optional ``cluster`` extra, imported only when used);
- ``run``: ``python -m companion fleet``, every recording of a fleet diagnosed, one task per file;
- ``work``: the task (one recording diagnosed on a worker);
- ``table``: the fleet table (CSV, Parquet) and its outliers;
- ``summary``: the HTML fleet summary.

This package's ``__init__`` imports nothing, so ``simvehicle.tools.sweep`` can use ``engine`` without
loading the diagnosis.
"""
