"""Publishing a run: the meshcat scene, its HTML page, the live viewer, and the plots."""
