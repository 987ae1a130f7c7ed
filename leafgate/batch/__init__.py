"""``leafgate batch``: simulation sweeps, log checks and session re-runs on Dask distributed."""
