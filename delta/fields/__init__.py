"""Neural fields: encodings, MLPs, the exterior NeRF, vertex fields and the deformation network."""

#: The exterior's layers, in the order of a layered NeRF's outputs (torch-free: the CLI offers them).
LAYERS = ("clothing", "hair")
