"""The engines: the per-execution loop and the batched lanes-last loop (storage and iteration only),
the batched engine's lane storage, dense-output weights and XLA:CPU work-arounds."""
