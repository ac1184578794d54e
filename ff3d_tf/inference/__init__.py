"""Inference and serving: any saved model as a predictor (checkpoint, SavedModel, ONNX, portable XLA), and the
forward's exports (SavedModel, ONNX, portable XLA programs with their TensorFlow-free runner; the lab times them)."""
