"""Silva's orchestration: configuration, the Dask cluster, the staged workflow, the CLI, reports."""
