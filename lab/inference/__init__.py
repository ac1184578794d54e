"""Measurements of inference: forward latency by compile mode (`latency`), ONNX Runtime beside TensorFlow
(`onnx_timing`), the portable XLA forward's timing and profile (`xla_timing`, `xla_profile`)."""
