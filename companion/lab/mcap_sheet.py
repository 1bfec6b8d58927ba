"""One picture of a flight log drawn with matplotlib: ``python -m companion.lab.mcap_sheet LOG OUT.png``.

For a report or an issue where no Foxglove is at hand: the colour image ``--at`` seconds from the log's
start with its annotations (the detections and the tracked leader, as the log's ``/camera/annotations`` has
them), the depth image beside it, the formation error over the whole log with every mission transition, and
the follower and the leader estimate from above (``/tf``). It draws only what the log holds.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.reader import make_reader

from companion.perception.sources.mcap_file import decode_colour, decode_depth_m, protobuf_class


def _read(path: Path, at_s: float | None) -> dict[str, Any]:
    """The messages the sheet needs (decoded), the image pair nearest ``at_s``."""
    import json  # noqa: PLC0415

    out: dict[str, Any] = {"err": [], "log": [], "tf": {"follower": [], "leader": []}, "images": []}
    classes: dict[int, Any] = {}
    start_ns: int | None = None
    with path.open("rb") as f:
        for schema, ch, m in make_reader(f).iter_messages(log_time_order=True):
            # Seconds from the log's first message (a simulator run's: its sim time, within a step).
            start_ns = m.log_time if start_ns is None else start_ns
            t_s = (m.log_time - start_ns) / 1e9
            if ch.topic == "/follower/formation":
                rec = json.loads(m.data)
                out["err"].append((t_s, rec.get("formation_error_m")))
                continue
            if schema is None or schema.encoding != "protobuf":
                continue
            cls = classes.get(ch.id)
            if cls is None:
                cls = classes[ch.id] = protobuf_class(schema.name, schema.data)
            if ch.topic == "/mission/log":
                out["log"].append((t_s, cls.FromString(m.data).message))
            elif ch.topic == "/tf":
                for tf in cls.FromString(m.data).transforms:
                    if tf.child_frame_id in ("follower", "leader"):
                        out["tf"][tf.child_frame_id].append((t_s, tf.translation.x, tf.translation.y))
            elif ch.topic in ("/camera/image", "/camera/depth", "/camera/annotations"):
                out["images"].append((t_s, ch.topic, schema.name, cls, m.data))
    times = sorted({t for t, topic, *_ in out["images"] if topic == "/camera/image"})
    if not times:
        raise SystemExit(f"mcap_sheet: {path} has no /camera/image")
    pick = times[-1] if at_s is None else min(times, key=lambda t: abs(t - at_s))
    chosen = {topic: (schema, cls, data) for t, topic, schema, cls, data in out["images"] if t == pick}
    out["t_image_s"] = pick
    out["chosen"] = chosen
    return out


def draw(path: Path, png: Path, at_s: float | None = None) -> None:
    """Write the sheet of ``path`` to ``png``."""
    import matplotlib as mpl  # noqa: PLC0415

    mpl.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    d = _read(path, at_s)
    schema, cls, data = d["chosen"]["/camera/image"]
    rgb = decode_colour(cls.FromString(data), schema).copy()
    if "/camera/annotations" in d["chosen"]:
        _, acls, adata = d["chosen"]["/camera/annotations"]
        ann = acls.FromString(adata)
        for pa in ann.points:
            pts = np.array([[p.x, p.y] for p in pa.points], np.int32)
            c = pa.outline_color
            cv2.polylines(
                rgb, [pts], True, (int(255 * c.r), int(255 * c.g), int(255 * c.b)), max(1, int(pa.thickness))
            )
        for ta in ann.texts:
            org = (int(ta.position.x), max(12, int(ta.position.y)))
            cv2.putText(rgb, ta.text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    fig = plt.figure(figsize=(14, 8.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1.0, 0.8])
    ax = fig.add_subplot(gs[0, 0:2])
    ax.imshow(rgb)
    ax.set_title(f"/camera/image + /camera/annotations at t = {d['t_image_s']:.2f} s")
    ax.axis("off")
    ax = fig.add_subplot(gs[0, 2])
    if "/camera/depth" in d["chosen"]:
        _, dcls, ddata = d["chosen"]["/camera/depth"]
        depth = decode_depth_m(dcls.FromString(ddata))
        im = ax.imshow(np.where(depth > 0, depth, np.nan), cmap="turbo", vmin=0.0, vmax=15.0)
        fig.colorbar(im, ax=ax, fraction=0.035, label="m")
    ax.set_title("/camera/depth")
    ax.axis("off")
    ax = fig.add_subplot(gs[1, 0:2])
    err = [(t, e) for t, e in d["err"] if e is not None]
    if err:
        ax.plot(*zip(*err, strict=True), lw=1.2, label="formation error (m)")
    for t_s, text in d["log"]:
        ax.axvline(t_s, color="tab:red" if "GPS lost" in text else "0.6", lw=0.8)
        ax.text(
            t_s,
            ax.get_ylim()[1] if err else 1.0,
            " " + text.split(": ", 1)[-1],
            rotation=90,
            va="top",
            fontsize=7,
        )
    ax.set_xlabel("log time (s)")
    ax.set_ylabel("m")
    ax.set_title("/follower/formation.formation_error_m and /mission/log")
    ax = fig.add_subplot(gs[1, 2])
    for frame, style in (("follower", "tab:blue"), ("leader", "tab:red")):
        pts = d["tf"][frame]
        if pts:
            _, x, y = zip(*pts, strict=True)
            ax.plot(x, y, color=style, lw=1.0, label=f"world -> {frame}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("/tf from above")
    ax.legend(fontsize=8)
    fig.suptitle(f"{path.name}: drawn from the log with matplotlib", fontsize=11)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)
    plt.close(fig)


def main() -> int:
    """Draw the sheet of one log."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument(
        "--at",
        type=float,
        default=None,
        help="the image nearest this time from the log's start, s (default: the last)",
    )
    args = p.parse_args()
    draw(args.log, args.out, args.at)
    print(f"mcap_sheet: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
