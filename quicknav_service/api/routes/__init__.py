"""One short module per resource: jobs (submit, list, cancel, delete), events (SSE), artifacts
(files, metrics history), maps (uploaded building maps), ops (health, readiness, presets, Prometheus)."""
