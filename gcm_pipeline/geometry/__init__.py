"""Pure geometry: dual quaternions and Delaunay triangulation (no robot)."""
