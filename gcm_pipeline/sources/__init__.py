"""Candidate sources: grasp generators, the antipodal sampler, grasp files, the gripper registry.

Each source gives poses (N, 4, 4) of the robot's grasp frame (the TCP: z =
approach, fingers closing along y, origin between the fingertips) and
per-candidate columns (:data:`gcm_pipeline.table.CANDIDATE_COLUMNS`):

- :mod:`~gcm_pipeline.sources.generators`: grasps placed on a primitive
  (``plane``, ``cylinder_side``, ``box``, ``sphere``);
- :mod:`~gcm_pipeline.sources.antipodal`: antipodal grasps sampled on a mesh
  or primitive for a gripper;
- :mod:`~gcm_pipeline.sources.files`: grasp files, one module per format,
  mapped onto the grasp frame by ``grasp_to_tool`` or the gripper registry
  (:mod:`~gcm_pipeline.sources.grippers`).

The functions take plain arguments; :func:`gcm_pipeline.pipeline.generate_candidates`
maps a config's ``candidates`` section onto them.

Importing this package imports nothing: the config reads the gripper names
(:mod:`~gcm_pipeline.sources.grippers`) without the file readers, h5py or
SciPy; import the names from their module.
"""
