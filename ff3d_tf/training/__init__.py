"""Training and evaluation: the training input, the tf.distribute loop, evaluation, the paper studies, and the training
step's portable XLA programs (export, and their TensorFlow-free runner; the lab times them)."""
