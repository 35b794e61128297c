"""Export: COLMAP models, nerfstudio transforms.json, point clouds, splats, meshes, renders, report."""
