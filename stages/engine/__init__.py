"""The DAG engine: stage nodes, their cache keys, cache entries and the scheduler (docs/cache.md). It knows no
stage and no Hydra: it runs `Stage(name, run, inputs)` nodes and hashes the code they import."""
