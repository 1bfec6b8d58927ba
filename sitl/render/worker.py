"""The camera server's render process: ``python -m sitl.render.worker``, spoken to over stdin/stdout.

moderngl holds the GIL while the GL driver works (a 30-80 ms frame on llvmpipe), which would stall a
real-time simulator sharing the process; so :class:`sitl.render.camera_server.CameraServer` renders here.

Protocol. stdin: one JSON line of configuration (``camera``, ``visual``, ``mount``, ``seed``,
``depth``), then one JSON line per frame: ``{"t": t_s, "f": pose, "l": pose or null, "dz": m}`` with
``pose = {"p": [n, e, d], "q": [w, x, y, z], "w": [p, q, r] or null}`` (``dz``, optional: a depth glitch
on the leader, sitl/render/faults.py). stdout: ``b"RDY1"`` once the
renderer is up, then one message per request in the wire format of
:mod:`companion.kernel.camera_wire`, ready to forward to clients as is. EOF on stdin ends it.
"""

from __future__ import annotations

import json
import sys
from typing import Any

import numpy as np

from companion.kernel.camera import MountConfig
from companion.kernel.camera_wire import encode_frame
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.faults import offset_leader_depth
from sitl.render.geometry import PoseTruth, VehiclePose
from sitl.render.renderer import Renderer

READY = b"RDY1"


def pose_to_json(pose: PoseTruth) -> dict[str, Any]:
    """The request form of a pose (with its body rate when it has one)."""
    omega = getattr(pose, "omega_body_rad_s", None)
    return {
        "p": [float(v) for v in np.asarray(pose.p_ned_m, dtype=np.float64)],
        "q": [float(v) for v in np.asarray(pose.q_ned_body_wxyz, dtype=np.float64)],
        "w": None if omega is None else [float(v) for v in np.asarray(omega, dtype=np.float64)],
    }


def pose_from_json(d: dict[str, Any]) -> VehiclePose:
    """Inverse of :func:`pose_to_json`."""
    w = d.get("w")
    return VehiclePose(
        np.array(d["p"], dtype=np.float64),
        np.array(d["q"], dtype=np.float64),
        None if w is None else np.array(w),
    )


def main() -> int:
    """Serve render requests from stdin until EOF."""
    stdin, out = sys.stdin.buffer, sys.stdout.buffer
    cfg = json.loads(stdin.readline())
    camera = CameraModel.model_validate(cfg["camera"])
    visual = VisualConfig.model_validate(cfg["visual"])
    mount = MountConfig.model_validate(cfg["mount"])
    with Renderer(camera, visual, mount, seed=int(cfg["seed"])) as renderer:
        out.write(READY)
        out.flush()
        for line in stdin:
            req = json.loads(line)
            leader = None if req["l"] is None else pose_from_json(req["l"])
            frame = renderer.render(pose_from_json(req["f"]), leader, float(req["t"]))
            if req.get("dz"):
                frame = offset_leader_depth(frame, float(req["dz"]))
            for part in encode_frame(frame, cfg["depth"]):
                out.write(part)
            out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
