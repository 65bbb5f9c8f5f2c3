"""The grasp manifold.

Triangles over the candidates, their blended surface, densification, adaptive
refinement, nearest-point queries, IK continuity and the reachable margin.
"""
