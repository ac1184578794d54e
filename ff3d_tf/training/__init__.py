"""Training and evaluation: the tf.distribute loop, the loss, the paper's metrics, evaluation and the paper studies."""
