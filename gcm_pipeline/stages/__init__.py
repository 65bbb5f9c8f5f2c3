"""Pipeline stages: candidates, manifold, densify, reachability, ranking, publish."""
