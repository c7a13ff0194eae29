"""XLA:CPU options of one compiled program (`jax.jit(..., compiler_options=...)`), not of the
process: hybridjax passes them to the programs it compiles itself and never changes `XLA_FLAGS`."""

# Kernels compiled by XLA:CPU's own fusion emitters rather than its MLIR ones: about half the
# compile time of a one-execution program, and of the small dense-output weights program.
FAST_COMPILE_CPU = {"xla_cpu_use_fusion_emitters": False}

# LLVM's loop vectorizer may use 512-bit vectors (XLA:CPU's default is 256; on a CPU without
# AVX-512 each is two 256-bit instructions, so the loop over the lanes is unrolled twice). A
# batch's kernels are loops over thousands of executions: with it the batched engine,
# `jax.vmap(simulate)` and their forward-mode derivatives run faster, a batch's reverse-mode
# derivative slower (FAQ: Compile time, "Batches: wider vectors").
WIDE_VECTORS_CPU = {"xla_cpu_prefer_vector_width": 512}

# Copy insertion with region analysis (XLA:GPU's default; off on XLA:CPU): an array carried
# through a while loop or a conditional is copied only where its old and new values are both
# live. A solve is loops within conditionals within loops, each carrying the state: with it
# XLA keeps a fifth fewer copies in the batched engine's program, and one execution, a batch
# and `jax.vmap(simulate)` run a few per cent faster, reverse mode as fast, in the same
# compile time (FAQ: Compile time, "Compiler settings, per program").
FEWER_COPIES_CPU = {"xla_cpu_copy_insertion_use_region_analysis": True}

# The options of a direct call's program (`hybridjax._solve.eager.eager_compiler_options`): one
# execution's, and a batch's without reverse mode.
ONE_EXECUTION_CPU = FAST_COMPILE_CPU | FEWER_COPIES_CPU
BATCH_CPU = WIDE_VECTORS_CPU | FEWER_COPIES_CPU
