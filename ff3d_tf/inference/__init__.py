"""Inference and serving: restoring a model (checkpoint or SavedModel), the compiled forward, SavedModel export."""
