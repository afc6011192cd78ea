"""Export a trained avatar: meshes (PLY, GLB), videos (mp4), side-by-side images and a line-up check."""
