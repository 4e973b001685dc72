"""Dense reconstruction: TSDF fusion of depth maps, meshes, surface scores and their picture."""
