"""VAMP's collision check on given configurations, run in VAMP's own venv.

Called by ``benchmarks/bench_limit.py`` as
``<vamp venv>/bin/python benchmarks/vamp/vamp_check.py IN.npz OUT.json``
(VAMP is no dependency of gcm_pipeline and this script imports nothing of it).

``IN.npz`` holds ``robot`` (VAMP's module name, e.g. ``panda``), ``scene``
(a JSON list of primitives: ``{"cuboid": {center, euler_xyz, half_extents}}``,
``{"capsule": {center, euler_xyz, radius, length}}`` (segment along the local
z), ``{"sphere": {center, radius}}``),
``q`` (N, dof) configurations checked one per call (``validate``: one SIMD
block whose lanes all hold the configuration), ``pairs`` (M, 2, dof): motions
checked with ``validate_motion`` (blocks of interpolated configurations at VAMP's
resolution), ``exact_collides`` (N,) the exact answer (empty: none): every configuration
on which VAMP disagrees with it is explained by ``debug`` (the names of the
primitives its spheres hit, and whether a self-collision pair is hit), and
``repeats``. Writes the validity of each configuration and
motion, and the median seconds per call of each loop, with the cost of an
empty binding call (``dimension()``) in the same loop for reference.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import numpy as np
import vamp


def environment(scene: list[dict]) -> vamp.Environment:
    env = vamp.Environment()
    for item in scene:
        ((kind, p),) = item.items()
        if kind == "cuboid":
            c = vamp.Cuboid(p["center"], p["euler_xyz"], p["half_extents"])
            c.name = p.get("name", "")
            env.add_cuboid(c)
        elif kind == "capsule":
            # (the binding's endpoints constructor assigns into unconstructed memory
            # and crashes in 0.6.4: the centre form is used)
            c = vamp.Cylinder(p["center"], p["euler_xyz"], p["radius"], p["length"])
            c.name = p.get("name", "")
            env.add_capsule(c)
        elif kind == "sphere":
            c = vamp.Sphere(p["center"], p["radius"])
            c.name = p.get("name", "")
            env.add_sphere(c)
        else:
            raise SystemExit(f"vamp_check: unknown primitive {kind!r}")
    return env


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    data = np.load(sys.argv[1])
    module = getattr(vamp, str(data["robot"]))
    env = environment(json.loads(str(data["scene"])))
    repeats = int(data["repeats"])
    qs = [list(map(float, q)) for q in np.asarray(data["q"], dtype=np.float32)]
    pairs = [
        (list(map(float, a)), list(map(float, b)))
        for a, b in np.asarray(data["pairs"], dtype=np.float32)
    ]
    validate, motion, dim = module.validate, module.validate_motion, module.dimension
    out: dict[str, object] = {"vamp_version": getattr(vamp, "__version__", "0.6.4")}
    dt, valid = timed(lambda: [validate(q, env) for q in qs], repeats)
    out["validate_s_per_call"] = dt / max(1, len(qs))
    out["valid"] = [bool(v) for v in valid]
    dt, _ = timed(lambda: [dim() for q in qs], repeats)
    out["empty_call_s"] = dt / max(1, len(qs))
    if pairs:
        dt, ok = timed(lambda: [motion(a, b, env) for a, b in pairs], repeats)
        out["validate_motion_s_per_call"] = dt / len(pairs)
        out["motion_valid"] = [bool(v) for v in ok]
    out["explain"] = []
    exact = np.asarray(data["exact_collides"], dtype=bool)
    disagree = np.flatnonzero(np.asarray(out["valid"]) == exact[: len(qs)]) if exact.size else []
    for i in disagree[:2000]:
        spheres, self_pairs = module.debug(qs[i], env)
        names = sorted({name for hits in spheres for name in hits})
        out["explain"].append({"index": int(i), "environment": names, "self": bool(self_pairs)})
    out["resolution"] = float(module.resolution())
    out["n_spheres"] = int(module.n_spheres())
    out["simd_lanes"] = 8
    with open(sys.argv[2], "w", encoding="utf-8") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
