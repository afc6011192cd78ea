"""Neural fields: encodings, MLPs, the exterior NeRF, vertex fields and the deformation network."""
