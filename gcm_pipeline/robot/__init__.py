"""Robot models, kinematics, inverse kinematics and manipulability.

* :mod:`~gcm_pipeline.robot.model`: parsed robot specs -> reduced Pinocchio
  models (:class:`~gcm_pipeline.robot.model.Robot`; by name or spec file:
  :func:`gcm_pipeline.config.robot_spec.load_robot`), forward kinematics and grasp-frame
  Jacobians (``LOCAL_WORLD_ALIGNED``);
* :mod:`~gcm_pipeline.robot.ik`: :func:`solve_ik` with the ``pinocchio``
  (batched LM, default) and ``mink`` backends, every success verified by
  Pinocchio forward kinematics;
* :mod:`~gcm_pipeline.robot.manipulability`: Yoshikawa (6-D and
  translational), inverse condition number, joint-limit margin.

Importing this package imports nothing: a module that needs the manipulability
metrics (or a robot model's file names) does not load Pinocchio, Numba or the
IK backends with them; import the names from their module. mink and MuJoCo
load only with :mod:`~gcm_pipeline.robot.ik.mink_backend`, when that backend
is used.
"""
