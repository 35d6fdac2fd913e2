"""Where the tasks run: the Dask cluster, the engine that maps a step's tasks on it, the
feature kernels compiled before the workers need them, and the watch that notices a cluster
on which no task can run."""
