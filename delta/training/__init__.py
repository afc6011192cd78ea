"""Training stages: data, presets, trainer, checkpoints."""
