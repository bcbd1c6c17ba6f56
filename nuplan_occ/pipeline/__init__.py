"""The build DAG runner: stage declarations, content-keyed cache, per-scene tasks, executors."""
