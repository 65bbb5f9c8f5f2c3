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
"""

from gcm_pipeline.sources.antipodal import (
    DEFAULT_FRICTION,
    antipodal_candidates,
    object_mesh,
    sample_antipodal,
)
from gcm_pipeline.sources.files import (
    ACRONYM_INSTALL_HINT,
    GRIPPER_FORMATS,
    IMPORT_FORMATS,
    ImportedGrasps,
    file_format,
    load_grasp_file,
    read_contact_graspnet,
    read_grasp_file,
    read_graspgen,
    read_graspnet,
    read_grasps,
    to_grasp_frame,
)
from gcm_pipeline.sources.generators import (
    GENERATORS,
    add_noise,
    generate,
    poses_box,
    poses_cylinder_side,
    poses_plane,
    poses_sphere,
)
from gcm_pipeline.sources.grippers import (
    CONVENTIONS,
    DATASET_GRIPPERS,
    GRIPPERS,
    GripperChoice,
    GripperSpec,
    choose_gripper,
    find_gripper,
    get_gripper,
    gripper_names,
)

__all__ = [
    "ACRONYM_INSTALL_HINT",
    "CONVENTIONS",
    "DATASET_GRIPPERS",
    "DEFAULT_FRICTION",
    "GENERATORS",
    "GRIPPERS",
    "GRIPPER_FORMATS",
    "IMPORT_FORMATS",
    "GripperChoice",
    "GripperSpec",
    "ImportedGrasps",
    "add_noise",
    "antipodal_candidates",
    "choose_gripper",
    "file_format",
    "find_gripper",
    "generate",
    "get_gripper",
    "gripper_names",
    "load_grasp_file",
    "object_mesh",
    "poses_box",
    "poses_cylinder_side",
    "poses_plane",
    "poses_sphere",
    "read_contact_graspnet",
    "read_grasp_file",
    "read_graspgen",
    "read_graspnet",
    "read_grasps",
    "sample_antipodal",
    "to_grasp_frame",
]
