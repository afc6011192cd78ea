"""Training stages: presets, trainer, checkpoints (the frames and rays they read: ``delta.data.frames``)."""
