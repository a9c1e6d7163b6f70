"""gRPC Rollout service: remote agents step batches of jit-compiled QuickNav envs over one stream."""
