"""Measurements of training: the training step's time and memory on CPUs (`cpu_step_study`, `cpu_studies`,
`bf16_study`, `head_cost`), the input's rates (`bench_input`, `bench_steps`), the exported step's timing
(`xla_step_timing`), the heads and distillation benchmarks and the fault soak."""
