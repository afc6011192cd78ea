"""The hybrid avatar composing body, fields, deformer and renderer."""
