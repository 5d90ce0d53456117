"""4. QR calibration (the paper's Table 3): accuracy of ``base_from_qr`` and its duration end
to end, through the robot client's skill code and the bench's vision server.

Accuracy: random views of the station's code from 0.6 to 1.5 m (up to 25° off its normal,
aimed within 3 cm of its centre, rolled up to ±0.3 rad; reachable ones only). At each view the
RGB-D camera captures one colour and 5 depth frames once; both methods measure on the same
frames with the skill's own measurement (``measure_qr_frame``: INSPECT ``station_pose`` = plane
method, or ``station_pose_corners`` = the paper's corner method, then base_from_qr =
base_from_camera @ camera_from_qr). Errors against the simulation's ground truth: translation
and rotation of base_from_qr, and the position error at the switch 0.5 m from the code (a point
taught in the QR frame). Two sensors: the example scene's (noise only) and the same with
systematic errors (depth misregistered against colour, depth scale bias of +0.5 % and the
goal's corners, -1 % and +1 %); the sensor-checked goal is judged on the worst of them.

Duration: the ``qr_calibration`` skill end to end at its view pose (no robot motion) with N
depth frames: camera time at 30 fps for 1 + N frames (a real camera cannot deliver faster;
rendering time is the simulation's and is left out), plus everything measured: two INSPECT
round trips (find the code, then its pose) and the client's work.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import (
    invert_transform,
    make_transform,
    rotation_from_axis_angle,
    rotation_from_rpy,
    transform_points,
)
from geometry.depth_registration import registration_advice
from simulation.hard_scenes import HardFamily, hard_views

from .cell import QR_TEXT, QR_VIEW, require
from .common import SCENE, Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .env import Env
from .plots import log_scale_if_positive, pyplot, save
from .servers import HOST
from .skills import FPS, ReplayCamera, TimedCamera, TimedVision

NAME = "calibration"
BIAS_VIEWS = 12
"""Views on which the QR corner detector's bias on the code's image side is measured against
the renderer's truth (as an integrator measures it against a known reference) for the
sensor-checked rows' ``corner_bias_px``. Measured each run, not a constant: it is a property of
the detector (-0.07 px when it was measured, -0.03 to -0.04 px after the corner refinement
was rewritten on a parallel branch; the stale -0.07 over-corrected the depth scale by ~0.04 %,
~0.4 mm at 1 m, the whole of the sensor-checked tail)."""
TITLE = "4. QR calibration: accuracy and duration"
METHODS = {
    "plane": "station_pose",
    "corners + side": "station_pose_corners",
    "corners, depth only (paper)": "station_pose_paper",
}
REFERENCE = "corners, depth only (paper)"
DISTANCE_M = (0.6, 1.5)
BANDS = ((0.6, 0.9), (0.9, 1.2), (1.2, 1.5))
MISREGISTRATION_PX = (2.0, 1.0)
SCALE_BIASES = (0.005, -0.01, 0.01)
"""The depth scale errors measured with ``MISREGISTRATION_PX``: the issue's example (+0.5 %)
and the goal's corners (+/-1 %); the goal is judged on the worst of them."""
PAPER_MM = 10.0
PAPER_S = 1.0
GOAL_T_MM, GOAL_R_DEG = 0.5, 0.2
GOAL_S, GOAL_COMPUTE_MS = 0.4, 40.0
PERFECT_BEFORE_T_MM, PERFECT_BEFORE_R_DEG = 0.084, 0.111
"""The perfect sensor's p95 in the sensor-check table before the unchecked fusion (bench at
e0dd99d, docs/BENCHMARKS.md): the unchecked goal keeps it at least as good."""
UNCHECKED = "plane, uncorrected"
UNCHECKED_BIAS = "plane, uncorrected, corner bias measured"
CHECKED = "plane, sensor-checked"
CHECK_KEYS = {UNCHECKED: "uncorrected", UNCHECKED_BIAS: "corner_bias", CHECKED: "sensor_checked"}
"""The sensor-check table's rows and their report keys (the first and last as before)."""
RESCALED = 1e-4
"""A view counts as rescaled to the side when the side moved its distance by more than this
(relative): the fusion always moves it a little (0.01 % is 0.1 mm at 1 m)."""
FloatArray = NDArray[np.float64]


@dataclasses.dataclass(frozen=True)
class Sensor:
    """The RGB-D camera's systematic errors: depth shifted ``misregistration_px`` (du, dv)
    against colour and read ``1 + scale_bias`` times the true z (None: the example scene's
    sensor, noise only). ``key`` names its bench values."""

    label: str
    key: str
    misregistration_px: tuple[float, float] | None = None
    scale_bias: float = 0.0

    @property
    def systematic(self) -> bool:
        return self.misregistration_px is not None


def _bias_key(bias: float) -> str:
    """The report key of a sensor with ``MISREGISTRATION_PX`` and ``bias``: +0.5 % keeps its
    earlier key ("systematic") so that the report's values stay comparable across runs."""
    if bias == 0.005:
        return "systematic"
    return f"systematic_{'plus' if bias > 0 else 'minus'}{abs(bias) * 100:g}pct".replace(".", "p")


SENSORS = (
    Sensor("noise only", "noise"),
    *(
        Sensor(
            f"+ misregistration {MISREGISTRATION_PX} px, depth bias {bias:+.1%}",
            _bias_key(bias),
            MISREGISTRATION_PX,
            bias,
        )
        for bias in SCALE_BIASES
    ),
)


def _scene(sensor: Sensor) -> Any:
    from simulation.scene import load_scene

    scene = load_scene(SCENE)
    if sensor.misregistration_px is None:
        return scene
    cameras = []
    for cam in scene.cameras:
        if cam.name == "rgbd" and cam.depth is not None:
            depth = dataclasses.replace(
                cam.depth,
                misregistration_px=sensor.misregistration_px,
                scale_bias=sensor.scale_bias,
            )
            cam = dataclasses.replace(cam, depth=depth)
        cameras.append(cam)
    return dataclasses.replace(scene, cameras=tuple(cameras))


def _view(cell: Any, rng: np.random.Generator) -> tuple[FloatArray, float] | None:
    """A tool pose whose RGB-D camera looks at the code (None: unreachable) and the distance."""
    board = cell.scene.qr_boards[0].world_from_board
    centre, normal = board[:3, 3], board[:3, 2]  # board z: out of the print
    axis = np.cross(normal, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    tilt = rotation_from_axis_angle(axis, rng.uniform(0.0, np.radians(25.0)))
    distance = float(rng.uniform(*DISTANCE_M))
    eye = centre + distance * (tilt @ normal)
    target = centre + board[:3, :2] @ rng.uniform(-0.03, 0.03, 2)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    roll = rotation_from_rpy(0.0, 0.0, rng.uniform(-0.3, 0.3))
    world_from_camera = make_transform(np.column_stack([x, np.cross(z, x), z]) @ roll, eye)
    tool_from_camera = cell.scene.camera("rgbd").pose
    base_from_tool = (
        invert_transform(cell.robot.world_from_base)
        @ world_from_camera
        @ invert_transform(tool_from_camera)
    )
    if not cell.robot.in_workspace(base_from_tool[:3, 3]):
        return None
    return base_from_tool, distance


@contextmanager
def _client(port: int) -> Iterator[Any]:
    from robot_client import SyncVisionClient

    client = SyncVisionClient(HOST, port)
    try:
        yield client
    finally:
        client.close()


def _accuracy(
    cfg: RunConfig, port: int, sensor: Sensor, views: int
) -> dict[str, dict[str, list[float]]]:
    from protocol import CellvisionError
    from robot_client.devices.sim import sim_devices
    from robot_client.skills import SkillContext
    from robot_client.skills.outcome import SkillFailed
    from robot_client.skills.qr_calibration import measure_qr_frame
    from robot_client.vision_geometry import rotation_error_rad
    from simulation import SimCell

    cell = SimCell(_scene(sensor), seed=31)
    base_from_world = invert_transform(cell.robot.world_from_base)
    truth = base_from_world @ cell.render("rgbd").truth.qr_codes["qr_station"].world_from_qr
    switch_world = cell.scene.switches[0].world_from_switch[:3, 3]
    p_switch_base = transform_points(base_from_world, switch_world).reshape(3)
    p_switch_qr = transform_points(invert_transform(truth), p_switch_base).reshape(3)
    out: dict[str, dict[str, list[float]]] = {
        m: {"t": [], "r": [], "poi": [], "d": [], "missed": [], "rescaled": []} for m in METHODS
    }
    rng = np.random.default_rng(77)  # the same views for both sensors
    with _client(port) as client:
        devices = sim_devices(cell, vision=TimedVision(client))
        ctx = SkillContext.create(devices)
        camera = devices.camera("rgbd")
        done = tries = 0
        while done < views and tries < 50 * views:
            tries += 1
            view = _view(cell, rng)
            if view is None:
                continue
            pose, distance = view
            cell.robot.move_linear(pose)
            replay = ReplayCamera(camera, camera.capture(depth_frames=5))  # type: ignore[arg-type]
            done += 1
            for method, inspection in METHODS.items():
                s = out[method]
                try:
                    m = measure_qr_frame(
                        ctx,
                        replay,
                        text=QR_TEXT,
                        qr_inspection=None,
                        pose_inspection=inspection,
                        depth_frames=5,
                        attempts=1,
                    )
                except SkillFailed:
                    s["missed"].append(distance)
                    continue
                except CellvisionError as exc:  # the server failed, not the method
                    raise Skip(
                        f"INSPECT {inspection} fails on the server: {exc.code.name}: {exc.message}"
                    ) from exc
                est = m.base_from_qr
                moved = abs(m.quality.get("scale", 1.0) - 1.0)
                s["rescaled"].append(float(moved > RESCALED))
                s["t"].append(float(np.linalg.norm(est[:3, 3] - truth[:3, 3])) * 1e3)
                s["r"].append(float(np.degrees(rotation_error_rad(est, truth))))
                poi = transform_points(est, p_switch_qr).reshape(3)
                s["poi"].append(float(np.linalg.norm(poi - p_switch_base)) * 1e3)
                s["d"].append(distance)
    return out


def _corner_bias(views: int) -> tuple[float, float]:
    """The detector's bias on the code's mean image side (px; mean and its standard error)
    over ``views`` views of the noise-only sensor, against the renderer's true corners (other
    views than the check's and the evaluation's)."""
    from simulation import SimCell
    from vision_server.analysis import qr_pose

    cell = SimCell(_scene(SENSORS[0]), seed=53)
    rng = np.random.default_rng(83)
    side = float(cell.scene.qr_boards[0].side_m)
    bias: list[float] = []
    while len(bias) < views:
        view = _view(cell, rng)
        if view is None:
            continue
        cell.robot.move_linear(view[0])
        frame = cell.render("rgbd")
        assert frame.depth is not None  # the RGB-D camera
        true_uv = frame.truth.qr_codes["qr_station"].corners_uv
        true_px = float(np.mean(np.linalg.norm(true_uv - np.roll(true_uv, -1, axis=0), axis=1)))
        found = qr_pose(
            frame.color, [frame.depth], frame.truth.intrinsics, expect=QR_TEXT, side_m=side
        )
        bias.append(found.quality.side_px - true_px)
    return float(np.mean(bias)), float(np.std(bias) / np.sqrt(len(bias)))


def _along_and_lateral_mm(camera_from_qr: FloatArray, truth: FloatArray) -> tuple[float, float]:
    """The translation error of ``camera_from_qr`` (the code's centre, camera frame) against
    ``truth`` split along the camera's ray through the true centre (signed: + is too far) and
    across it, in mm. The bench scores the centre itself, so the rotation adds no lever arm
    there; a distance error (depth scale, the printed side) lies along the ray, a
    misregistration or a corner error across it."""
    error = camera_from_qr[:3, 3] - truth[:3, 3]
    ray = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    along = float(error @ ray)
    lateral = float(np.linalg.norm(error - along * ray))
    return along * 1e3, lateral * 1e3


def _sensor_check(
    views: int,
    evaluated: int,
    corner_bias_px: float,
    sensors: tuple[Sensor, ...] = SENSORS,
) -> dict[Sensor, dict[str, Any]]:
    """The sensor check and its correction, in process (the analysis the server runs): per
    sensor of ``sensors``, ``views`` views fit scale and shift (fit_depth_registration), then
    ``evaluated`` other views are measured by the plane method without and with that
    correction. Errors of camera_from_qr against the simulation's truth: translation mm,
    rotation degrees."""
    from robot_client.vision_geometry import rotation_error_rad
    from simulation import SimCell
    from vision_server.analysis import fit_depth_registration, qr_pose

    out: dict[Sensor, dict[str, Any]] = {}
    for sensor in sensors:
        cell = SimCell(_scene(sensor), seed=37)
        rng = np.random.default_rng(79)  # the same views for both sensors
        side = float(cell.scene.qr_boards[0].side_m)
        measured: list[tuple[Any, Any, FloatArray]] = []
        true_uv: list[FloatArray] = []
        while len(measured) < views + evaluated:
            view = _view(cell, rng)
            if view is None:
                continue
            cell.robot.move_linear(view[0])
            frames = [cell.render("rgbd") for _ in range(5)]
            code = frames[0].truth.qr_codes["qr_station"]
            measured.append((frames[0], [f.depth for f in frames], code.camera_from_qr))
            true_uv.append(code.corners_uv)
        check = [
            qr_pose(f.color, d, f.truth.intrinsics, expect=QR_TEXT, side_m=side).quality
            for f, d, _ in measured[:views]
        ]
        reg = fit_depth_registration(
            [q.depth_vs_side for q in check],
            [[float(g) for g in q.shift_sensitivity] for q in check],
            [q.side_px for q in check],
            corner_bias_px=corner_bias_px,
            depth_vs_grid=[q.depth_vs_grid for q in check],
        )
        rows: dict[str, Any] = {"registration": reg}
        corrections: dict[str, dict[str, Any]] = {
            UNCHECKED: {},
            # what an integrator has without a sensor check but with the detector's bias
            # measured once against a known reference
            UNCHECKED_BIAS: {"corner_bias_px": corner_bias_px},
            CHECKED: {
                "depth_scale": reg.scale,
                "depth_shift_px": reg.shift_px,
                "depth_scale_std": reg.scale_std,
                "depth_shift_std_px": reg.shift_std_px,
                "corner_bias_px": corner_bias_px,
            },
        }
        for name, kw in corrections.items():
            t, r = [], []
            for f, d, truth in measured[views:]:
                pose = qr_pose(
                    f.color,
                    d,
                    f.truth.intrinsics,
                    expect=QR_TEXT,
                    side_m=side,
                    **kw,
                ).camera_from_qr
                t.append(float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])) * 1e3)
                r.append(float(np.degrees(rotation_error_rad(pose, truth))))
            rows[name] = {"t": t, "r": r}
        rows["decomposition"] = _decomposition(measured[views:], true_uv[views:], side)
        out[sensor] = rows
    return out


def _decomposition(
    measured: list[tuple[Any, Any, FloatArray]], true_uv: list[FloatArray], side_m: float
) -> dict[str, list[float]]:
    """Where the unchecked plane method's error comes from, per evaluated view: its error
    along the ray and across it (mm, :func:`_along_and_lateral_mm`), the same along the ray
    with the distance from the depth alone (``scale="depth"``) and from the printed side
    alone (``scale="side"``), and the detector's error on the code's mean image side against
    the renderer's true corners (px; negative: read short, which puts the code too far)."""
    from vision_server.analysis import qr_pose

    out: dict[str, list[float]] = {
        k: [] for k in ("along", "lateral", "depth_along", "side_along", "side_px_error")
    }
    for (f, d, truth), uv in zip(measured, true_uv, strict=True):
        poses = {
            k: qr_pose(f.color, d, f.truth.intrinsics, expect=QR_TEXT, side_m=side_m, scale=k)
            for k in ("auto", "depth", "side")
        }
        along, lateral = _along_and_lateral_mm(poses["auto"].camera_from_qr, truth)
        out["along"].append(along)
        out["lateral"].append(lateral)
        out["depth_along"].append(_along_and_lateral_mm(poses["depth"].camera_from_qr, truth)[0])
        out["side_along"].append(_along_and_lateral_mm(poses["side"].camera_from_qr, truth)[0])
        true_side = float(np.mean(np.linalg.norm(uv - np.roll(uv, -1, axis=0), axis=1)))
        out["side_px_error"].append(poses["auto"].quality.side_px - true_side)
    return out


def _unchecked_goals(section: Section, checked: dict[Sensor, dict[str, Any]]) -> None:
    """The goal without a sensor check (nothing configured): judged on the worst systematic
    sensor, and the perfect sensor kept at least as good as before the unchecked fusion; the
    same with the detector's corner bias measured, beside it."""
    perfect = next(rows for sensor, rows in checked.items() if not sensor.systematic)
    systematic = {s: rows for s, rows in checked.items() if s.systematic}
    for method, what in (
        (UNCHECKED, "nothing configured"),
        (UNCHECKED_BIAS, "only corner_bias_px"),
    ):
        t = {s: Stats.of(rows[method]["t"]).p95 for s, rows in systematic.items()}
        r = {s: Stats.of(rows[method]["r"]).p95 for s, rows in systematic.items()}
        worst_t, worst_r = max(t, key=t.__getitem__), max(r, key=r.__getitem__)
        clean_t = Stats.of(perfect[method]["t"]).p95
        clean_r = Stats.of(perfect[method]["r"]).p95
        key = CHECK_KEYS[method]
        section.value(f"unchecked_{key}_worst_t_p95_mm", t[worst_t])
        section.value(f"unchecked_{key}_worst_r_p95_deg", r[worst_r])
        section.goals.append(
            Goal(
                f"plane method without a sensor check ({what}), p95 <= {GOAL_T_MM} mm and "
                f"<= {GOAL_R_DEG}° on every sensor with misregistration {MISREGISTRATION_PX} px "
                f"and depth scale {', '.join(f'{b:+.1%}' for b in SCALE_BIASES)}",
                f"worst {fmt(t[worst_t])} mm ({worst_t.label}), {fmt(r[worst_r])}° "
                f"({worst_r.label}); "
                + "; ".join(f"{s.label}: {fmt(t[s])} mm, {fmt(r[s])}°" for s in systematic),
                t[worst_t] <= GOAL_T_MM and r[worst_r] <= GOAL_R_DEG,
            )
        )
        section.goals.append(
            Goal(
                f"plane method without a sensor check ({what}), perfect sensor no worse than "
                f"before the unchecked fusion ({PERFECT_BEFORE_T_MM} mm, "
                f"{PERFECT_BEFORE_R_DEG}° p95)",
                f"{fmt(clean_t)} mm, {fmt(clean_r)}°",
                # the figures before are the report's, rounded to 3 decimals: compared at that
                # precision (the rotation does not depend on the distance at all, and read
                # 0.1110x > 0.111 unchanged)
                round(clean_t, 3) <= PERFECT_BEFORE_T_MM
                and round(clean_r, 3) <= PERFECT_BEFORE_R_DEG,
            )
        )


def _decomposition_table(section: Section, checked: dict[Sensor, dict[str, Any]]) -> Table:
    """The unchecked rows' error split (:func:`_decomposition`) as a table, with its values."""
    table = Table(
        [
            "sensor",
            "unchecked: along the ray mean ± std, |·| p95 mm",
            "across p95 mm",
            "depth alone: along mean, |·| p95 mm",
            "printed side alone: along mean, |·| p95 mm",
            "detector's side error px: mean, view-to-view std",
        ],
        caption="Where the unchecked error comes from (plane method, nothing configured; the "
        "code's centre in the camera frame, split along the camera's ray and across it):",
    )
    for sensor, rows in checked.items():
        dec = {k: np.asarray(v) for k, v in rows["decomposition"].items()}
        along, side_px = dec["along"], dec["side_px_error"]
        p95 = {k: float(np.percentile(np.abs(v), 95)) for k, v in dec.items()}
        table.add(
            sensor.label,
            f"{along.mean():+.3f} ± {along.std():.3f}, {fmt(p95['along'])}",
            fmt(p95["lateral"]),
            f"{dec['depth_along'].mean():+.3f}, {fmt(p95['depth_along'])}",
            f"{dec['side_along'].mean():+.3f}, {fmt(p95['side_along'])}",
            f"{side_px.mean():+.3f}, {side_px.std():.3f}",
        )
        key = f"decomposition_{sensor.key}"
        section.value(f"{key}_along_p95_mm", p95["along"])
        section.value(f"{key}_lateral_p95_mm", p95["lateral"])
        section.value(f"{key}_side_along_p95_mm", p95["side_along"])
        section.value(f"{key}_side_px_error_std", float(side_px.std()))
    return table


def _durations(port: int, frames: tuple[int, ...], runs: int) -> dict[int, dict[str, list[float]]]:
    from robot_client.devices.sim import sim_devices
    from robot_client.skills import SkillContext, default_registry, execute
    from simulation import SimCell

    skill = default_registry().get("qr_calibration")
    out: dict[int, dict[str, list[float]]] = {}
    with _client(port) as client:
        for n in frames:
            cell = SimCell.from_yaml(SCENE, seed=41)
            vision = TimedVision(client)
            devices = sim_devices(cell, vision=vision)
            camera = TimedCamera(cell, "rgbd")
            devices.cameras["rgbd"] = camera
            ctx = SkillContext.create(devices)
            ctx.robot.move_linear(QR_VIEW)
            record = skill.teach("station", {"text": QR_TEXT, "depth_frames": n}, ctx)
            rows: dict[str, list[float]] = {
                k: [] for k in ("camera", "vision", "compute", "client", "total")
            }
            for _ in range(runs):
                vision.calls.clear()
                frames0, render0 = camera.frames, camera.render_ms
                t0 = time.perf_counter()
                outcome = execute(skill, record, ctx)
                wall = (time.perf_counter() - t0) * 1000.0
                if not outcome.ok:
                    raise Skip(f"qr_calibration failed with {n} depth frames: {outcome.message}")
                camera_ms = (camera.frames - frames0) / FPS * 1000.0
                vision_ms = sum(c.wall_ms for c in vision.calls)
                rest = wall - (camera.render_ms - render0) - vision_ms
                rows["camera"].append(camera_ms)
                rows["vision"].append(vision_ms)
                rows["compute"].append(sum(c.compute_ms for c in vision.calls))
                for call in vision.calls:
                    rows.setdefault(f"compute {call.inspection}", []).append(call.compute_ms)
                rows["client"].append(rest)
                rows["total"].append(camera_ms + vision_ms + rest)
            out[n] = rows
    return out


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    server = env.server("cellvision")
    wanted = (*METHODS.values(), "station_qr")
    missing = [i for i in wanted if i not in server.info["inspections"]]
    if missing:
        require(env.catalog, *missing)
    views = cfg.n(40, 2)
    results = {sensor: _accuracy(cfg, server.port, sensor, views) for sensor in SENSORS}
    table = Table(
        [
            "sensor",
            "method",
            "views",
            "missed",
            "translation p50 / p95 / max mm",
            "rotation p50 / p95 deg",
            "switch (0.5 m) p50 / p95 / max mm",
            "switch p95 ÷ paper ±10 mm",
            "switch p95 ÷ paper's method",
            "rescaled to the side",
        ]
    )
    for sensor, by_method in results.items():
        label = sensor.label
        paper_poi = Stats.of(by_method[REFERENCE]["poi"]).p95
        for method, s in by_method.items():
            t, r, poi = Stats.of(s["t"]), Stats.of(s["r"]), Stats.of(s["poi"])
            table.add(
                label,
                method,
                t.n + len(s["missed"]),
                len(s["missed"]),
                f"{fmt(t.p50)} / {fmt(t.p95)} / {fmt(t.max)}",
                f"{fmt(r.p50)} / {fmt(r.p95)}",
                f"{fmt(poi.p50)} / {fmt(poi.p95)} / {fmt(poi.max)}",
                ratio(poi.p95, PAPER_MM),
                ratio(poi.p95, paper_poi),
                f"{int(sum(s['rescaled']))} of {len(s['rescaled'])}",
            )
            short = {"plane": "plane", "corners + side": "corners_side"}.get(method, "paper")
            key = f"{sensor.key}_{short}"
            section.value(f"{key}_t_p95_mm", t.p95)
            section.value(f"{key}_r_p95_deg", r.p95)
            section.value(f"{key}_poi_p95_mm", poi.p95)
            section.value(f"{key}_missed", len(s["missed"]))
        plane = by_method["plane"]
        t95, r95 = Stats.of(plane["t"]).p95, Stats.of(plane["r"]).p95
        section.goals.append(
            Goal(
                f"plane method p95 <= {GOAL_T_MM} mm and <= {GOAL_R_DEG}° ({label})",
                f"{fmt(t95)} mm, {fmt(r95)}°",
                t95 <= GOAL_T_MM and r95 <= GOAL_R_DEG,
            )
        )
        worst = max(Stats.of(s["poi"]).p95 for s in by_method.values())
        section.goals.append(
            Goal(
                f"every method within the paper's ±{PAPER_MM:g} mm at the switch, p95 ({label})",
                ", ".join(f"{m} {fmt(Stats.of(s['poi']).p95)} mm" for m, s in by_method.items()),
                worst <= PAPER_MM,
            )
        )
    bands = Table(
        ["sensor", "method", *[f"{a}-{b} m: n, switch p95 mm" for a, b in BANDS]],
        caption="By distance to the code:",
    )
    for sensor, by_method in results.items():
        for method, s in by_method.items():
            d, poi_mm = np.asarray(s["d"]), np.asarray(s["poi"])
            cells = []
            for lo, hi in BANDS:
                sel = poi_mm[(d >= lo) & (d < hi)]
                cells.append(f"{sel.size}, {fmt(Stats.of(sel).p95)}")
            bands.add(sensor.label, method, *cells)

    bias_px, bias_se = _corner_bias(cfg.n(BIAS_VIEWS, 2))
    section.value("corner_bias_px", bias_px)
    checked = _sensor_check(cfg.n(12, 4), cfg.n(30, 4), bias_px)
    check_table = Table(
        [
            "sensor",
            "sensor check: scale, shift px (± std)",
            "method",
            "views",
            "translation p50 / p95 mm",
            "rotation p95 deg",
            f"p95 ÷ goal {GOAL_T_MM} mm",
        ],
        caption="Sensor check and correction (in process; camera_from_qr against the truth; "
        "the check's views are not the evaluated ones):",
    )
    clean_p95 = float("nan")
    advised: dict[Sensor, tuple[str, Stats, Stats]] = {}
    for sensor, rows in checked.items():
        reg = rows["registration"]
        fitted = (
            f"{reg.scale:.4f} ± {reg.scale_std:.4f}, ({reg.shift_px[0]:+.2f}, "
            f"{reg.shift_px[1]:+.2f}) ± ({reg.shift_std_px[0]:.2f}, {reg.shift_std_px[1]:.2f})"
        )
        # what an integrator configures: the correction only when the check asks for it
        within, _ = registration_advice(reg)
        chosen = UNCHECKED if within else CHECKED
        for method in CHECK_KEYS:
            t, r = Stats.of(rows[method]["t"]), Stats.of(rows[method]["r"])
            check_table.add(
                sensor.label,
                fitted,
                method + (" (advised)" if method == chosen else ""),
                t.n,
                f"{fmt(t.p50)} / {fmt(t.p95)}",
                fmt(r.p95),
                ratio(t.p95, GOAL_T_MM),
            )
            key = f"check_{sensor.key}_{CHECK_KEYS[method]}"
            section.value(f"{key}_t_p95_mm".replace("-", "_"), t.p95)
            section.value(f"{key}_r_p95_deg".replace("-", "_"), r.p95)
            if method == chosen:
                advised[sensor] = (method, t, r)
        if not sensor.systematic:
            clean_p95 = Stats.of(rows[UNCHECKED]["t"]).p95
        else:
            section.value(f"check_{sensor.key}_scale", reg.scale)
            section.value(f"check_{sensor.key}_shift_u_px", reg.shift_px[0])
            section.value(f"check_{sensor.key}_shift_v_px", reg.shift_px[1])
    # the goal holds at its corners, so it is judged on the worst sensor, not on each alone
    worst_t = max(advised, key=lambda k: advised[k][1].p95)
    worst_r = max(advised, key=lambda k: advised[k][2].p95)
    t95, r95 = advised[worst_t][1].p95, advised[worst_r][2].p95
    section.value("check_worst_t_p95_mm", t95)
    section.value("check_worst_r_p95_deg", r95)
    section.goals.append(
        Goal(
            f"plane method as the sensor check advises, p95 <= {GOAL_T_MM} mm and "
            f"<= {GOAL_R_DEG}° on every sensor (worst of {len(advised)}: misregistration up to "
            f"{MISREGISTRATION_PX} px, depth scale {', '.join(f'{b:+.1%}' for b in SCALE_BIASES)}"
            ", and noise only)",
            f"worst {fmt(t95)} mm ({worst_t.label}), {fmt(r95)}° ({worst_r.label}); "
            + "; ".join(
                f"{k.label}: {m.split(', ')[1]} {fmt(t.p95)} mm, {fmt(r.p95)}°"
                for k, (m, t, r) in advised.items()
            ),
            t95 <= GOAL_T_MM and r95 <= GOAL_R_DEG,
        )
    )
    _unchecked_goals(section, checked)
    decomposition = _decomposition_table(section, checked)
    hard_table = _hard_table(section, _hard_scenes(cfg.n(20, 2), cfg.n(12, 4), bias_px))
    section.notes.append(
        "Hard scenes: each family's own sensor check (12 other views of that camera and scene) "
        "gives the sensor-checked rows' correction. The tilt is fused from the depth's plane "
        "and the code's corners (PnP on the module grid's corners) by their covariances "
        '(vision_server/analysis/qr_tilt.py); the rows "the depth\'s tilt alone" are '
        'qr_pose\'s `normal="depth"`, the plane method as it was before. The families marked '
        "(reported) are not judged against the goal: they are limited by the depth's noise or "
        "by the distance, not by the sensor's systematic errors (a sensor without them does "
        "no better there with the depth's tilt alone), and some miss it."
    )
    section.notes.append(
        "Sensor check: `fit_depth_registration` over the check's views fits the depth scale and "
        "the depth-to-colour shift against the printed side (what `vision-server sensor-check` "
        "prints); the corrected rows pass them and their standard errors as `depth_scale` / "
        "`depth_shift_px` / `depth_scale_std` / `depth_shift_std_px`. Without "
        "sensor errors the uncorrected plane method stays the default (its p95 here "
        f"{fmt(clean_p95)} mm); no correction is configured unless the check says so. "
        f"`corner_bias_px` {bias_px:+.3f} ± {bias_se:.3f} px: the detector's bias on the "
        "code's image side, measured this run against the renderer's true corners on "
        f"{cfg.n(BIAS_VIEWS, 2)} other views (what an integrator measures once against a "
        "known reference)."
    )

    frames = (1, 3, 5, 10) if not cfg.quick else (1,)
    durations = _durations(server.port, frames, cfg.n(5, 1))
    timing = Table(
        [
            "depth frames N",
            "camera (1 + N frames at 30 fps) ms",
            "vision round trips ms",
            "of which server compute ms",
            "client ms",
            "end to end ms",
            "÷ paper 1 s",
            f"÷ goal {GOAL_S} s",
        ],
        caption="Duration of one qr_calibration at its view pose (medians):",
    )
    for n, rows in durations.items():
        med = {k: float(np.median(v)) for k, v in rows.items()}
        timing.add(
            n,
            fmt(med["camera"], 1),
            fmt(med["vision"], 1),
            fmt(med["compute"], 1),
            fmt(med["client"], 1),
            fmt(med["total"], 1),
            ratio(med["total"], PAPER_S * 1000.0),
            ratio(med["total"], GOAL_S * 1000.0),
        )
        section.value(f"duration_n{n}_ms", med["total"])
        section.value(f"compute_n{n}_ms", med["compute"])
    n_goal = 5 if 5 in durations else frames[0]
    total = float(np.median(durations[n_goal]["total"]))
    compute = float(np.median(durations[n_goal]["compute"]))
    parts = ", ".join(
        f"{k.split(' ', 1)[1]} {fmt(float(np.median(v)), 1)} ms"
        for k, v in durations[n_goal].items()
        if k.startswith("compute ")
    )
    section.goals.append(
        Goal(
            f"calibration <= {GOAL_S} s end to end (N = {n_goal} depth frames; paper "
            f"< {PAPER_S:g} s)",
            f"{fmt(total / 1000.0, 3)} s = {ratio(total, PAPER_S * 1000.0)} the paper's bar",
            total <= GOAL_S * 1000.0,
        )
    )
    section.goals.append(
        Goal(
            f"calibration compute <= {GOAL_COMPUTE_MS:g} ms (server compute_ms of both "
            f"INSPECTs, N = {n_goal})",
            f"{fmt(compute, 1)} ms ({parts})",
            compute <= GOAL_COMPUTE_MS,
        )
    )
    section.intro = (
        f"{views} views per sensor, colour + 5 depth frames each, measured by the skill's "
        "`measure_qr_frame` through three `qr_pose` inspections on the same frames: "
        "`station_pose` (plane method with the printed side of 0.16 m, as configured in "
        "examples/cell.yaml, no sensor check configured: the distance fuses the depth's and the "
        "printed side's, assuming an unchecked sensor's typical errors, 1 % scale and 2 px "
        "registration, and keeping the depth's distance while it agrees with the side within "
        "3 of the side's stds; `_unchecked_factor` of vision_server/analysis/qr_pose.py; the "
        "code's size from its module grid, vision_server/analysis/qr_grid.py), "
        "`station_pose_corners` (the corner method with the same side) "
        "and `station_pose_paper` (the paper's equations 1-4 exactly: the corners' depths, no "
        "rescaling; the reference). Ground truth from the simulation. "
        "The systematic sensors shift depth by "
        f"{MISREGISTRATION_PX} px against colour and scale it by "
        f"{', '.join(f'{1 + b:g}' for b in SCALE_BIASES)} (the issue's example and the goal's "
        "corners)."
    )
    section.tables += [table, bands, check_table, decomposition, hard_table, timing]
    section.notes.append(
        "Compute is the server's `compute_ms` of both INSPECTs (`station_qr` to find the "
        'code, `station_pose` for its pose), as reported in their RESULTs. "Rescaled to the '
        "side\" counts the views where the printed side moved the depth's distance by more "
        f"than {RESCALED:.2%} (`quality.scale`; the fusion weighs the two by their "
        "uncertainties, so it moves every view a little): a sensor without systematic errors "
        "keeps the depth's distance unless the side's noise makes them disagree; with errors, "
        "a view left unscaled keeps the error, which grows with the distance."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, 3, figsize=(15, 4))
        for sensor, by_method in results.items():
            for method, s in by_method.items():
                style = {"plane": "o", "corners + side": "+"}.get(method, "x")
                short = sensor.key.replace("_", " ")
                axes[0].plot(s["d"], s["t"], style, ms=4, label=f"{method}, {short}")
                axes[1].plot(s["d"], s["poi"], style, ms=4, label=f"{method}, {short}")
        for ax, what in zip(
            axes[:2], ("base_from_qr translation", "switch 0.5 m away"), strict=True
        ):
            log_scale_if_positive(ax)
            ax.set_xlabel("distance to the code [m]")
            ax.set_ylabel(f"{what} error [mm]")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        axes[1].axhline(PAPER_MM, color="grey", linestyle="--")
        ns = list(durations)
        bottom = np.zeros(len(ns))
        for part in ("camera", "vision", "client"):
            heights = np.array([np.median(durations[n][part]) for n in ns])
            axes[2].bar([str(n) for n in ns], heights, bottom=bottom, label=part)
            bottom += heights
        axes[2].axhline(GOAL_S * 1000.0, color="grey", linestyle="--", label="goal 0.4 s")
        axes[2].set_xlabel("depth frames N")
        axes[2].set_ylabel("end to end [ms]")
        axes[2].legend(fontsize=7)
        return [save(fig, directory / "calibration.png")]

    section.plot = plot
    return section


# --- hard scenes (issue 29 part 4) ---------------------------------------------------------

HARD_SCALE_BIAS = 0.005


HARD_FAMILIES = (
    HardFamily("oblique 30-45°", tilt_deg=(30.0, 45.0)),
    HardFamily("code near the image border", off_centre=0.85),
    HardFamily(
        "plate 8 cm off the wall, 12 mm margin",
        (0.6, 1.2),
        (0.0, 40.0),
        margin_m=0.012,
        standoff_m=0.08,
    ),
    HardFamily(
        "D435-like 1280x720, fb 45.5 px m",
        (0.6, 1.5),
        (0.0, 40.0),
        0.5,
        (1280, 720),
        910.0,
        fb_px_m=0.05 * 910.0,
        sigma_d_px=0.08,
    ),
    HardFamily("10 % depth holes", dropout=0.1),
    HardFamily(
        "lens distortion (k1 -0.08)", off_centre=0.6, dist=(-0.08, 0.05, 0.0004, -0.0003, 0.0)
    ),
    HardFamily("oblique 45-60°", tilt_deg=(45.0, 60.0), goal=False),
    HardFamily("far, 1.5-2.5 m", (1.5, 2.5), goal=False),
    HardFamily("small code 6 cm", side_m=0.06, margin_m=0.012, goal=False),
    HardFamily(
        "D405-like 1280x720 at 0.2-0.45 m, 5 cm code",
        (0.2, 0.45),
        (0.0, 40.0),
        0.5,
        (1280, 720),
        650.0,
        fb_px_m=0.018 * 650.0,
        sigma_d_px=0.05,
        near_m=0.07,
        side_m=0.05,
        margin_m=0.01,
        goal=False,
    ),
)
HARD_ROWS = {
    "unchecked": "plane, uncorrected",
    "checked": "plane, sensor-checked",
    "unchecked_depth_tilt": "plane, uncorrected, the depth's tilt alone (before issue 29)",
    "checked_depth_tilt": "plane, sensor-checked, the depth's tilt alone (before issue 29)",
}


def _hard_views(family: HardFamily, count: int, seed: int) -> list[tuple[Any, Any, FloatArray]]:
    """``count`` views (colour frame, 5 depth frames, true camera_from_qr) with the code wholly
    in the image, misregistered MISREGISTRATION_PX and scaled by HARD_SCALE_BIAS."""
    return hard_views(
        family,
        count,
        seed=seed,
        frames=5,
        shift_px=MISREGISTRATION_PX,
        scale_bias=HARD_SCALE_BIAS,
        text=QR_TEXT,
    )


def _hard_scenes(views: int, check_views: int, corner_bias_px: float) -> dict[str, Any]:
    """Per family: a sensor check on ``check_views`` views (its fit of scale and shift), then
    ``views`` other views measured unchecked and with the check's correction, each with the
    tilt fused from the depth and the corners (the default) and with the depth's tilt alone.
    Errors of camera_from_qr against the truth: translation mm, rotation degrees; views where
    qr_pose found nothing are counted, not scored."""
    from robot_client.vision_geometry import rotation_error_rad
    from vision_server.analysis import AnalysisError, fit_depth_registration, qr_pose

    out: dict[str, Any] = {}
    for family in HARD_FAMILIES:
        seed = zlib.crc32(family.name.encode())  # the same views whichever families run
        check = _hard_views(family, check_views, seed)
        evaluated = _hard_views(family, views, seed + 1)
        kw: dict[str, Any] = {"expect": QR_TEXT, "side_m": family.side_m}
        qualities = []
        for f, d, _ in check:
            try:
                qualities.append(qr_pose(f.color, d, f.truth.intrinsics, **kw).quality)
            except AnalysisError:
                continue
        reg = fit_depth_registration(
            [q.depth_vs_side for q in qualities],
            [[float(g) for g in q.shift_sensitivity] for q in qualities],
            [q.side_px for q in qualities],
            corner_bias_px=corner_bias_px,
            depth_vs_grid=[q.depth_vs_grid for q in qualities],
        )
        correction = {
            "depth_scale": reg.scale,
            "depth_shift_px": reg.shift_px,
            "depth_scale_std": reg.scale_std,
            "depth_shift_std_px": reg.shift_std_px,
            "corner_bias_px": corner_bias_px,
        }
        configs: dict[str, dict[str, Any]] = {
            "unchecked": {},
            "checked": correction,
            "unchecked_depth_tilt": {"normal": "depth"},
            "checked_depth_tilt": {**correction, "normal": "depth"},
        }
        rows: dict[str, Any] = {"registration": reg, "views": len(evaluated)}
        for name, extra in configs.items():
            t, r, missed = [], [], 0
            for f, d, truth in evaluated:
                try:
                    pose = qr_pose(f.color, d, f.truth.intrinsics, **kw, **extra).camera_from_qr
                except AnalysisError:
                    missed += 1
                    continue
                t.append(float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])) * 1e3)
                r.append(float(np.degrees(rotation_error_rad(pose, truth))))
            rows[name] = {"t": t, "r": r, "missed": missed}
        out[family.name] = rows
    return out


def _hard_table(section: Section, hard: dict[str, Any]) -> Table:
    """The hard scenes' table, their values and the goal on the families it is judged on."""
    table = Table(
        [
            "scene",
            "sensor check: scale, shift px",
            "method",
            "views (missed)",
            "translation p50 / p95 mm",
            "rotation p50 / p95 deg",
        ],
        caption="Hard scenes (issue 29 part 4; in process; depth misregistered "
        f"{MISREGISTRATION_PX} px and scaled {HARD_SCALE_BIAS:+.1%}; camera_from_qr against "
        "the truth):",
    )
    worst = {"unchecked": (0.0, 0.0), "checked": (0.0, 0.0)}
    for family in HARD_FAMILIES:
        rows = hard[family.name]
        reg = rows["registration"]
        fitted = f"{reg.scale:.4f}, ({reg.shift_px[0]:+.2f}, {reg.shift_px[1]:+.2f})"
        for key, label in HARD_ROWS.items():
            s = rows[key]
            t, r = Stats.of(s["t"]), Stats.of(s["r"])
            table.add(
                family.name + ("" if family.goal else " (reported)"),
                fitted,
                label,
                f"{t.n} ({s['missed']})",
                f"{fmt(t.p50)} / {fmt(t.p95)}",
                f"{fmt(r.p50)} / {fmt(r.p95)}",
            )
            slug = "".join(ch if ch.isalnum() else "_" for ch in family.name.lower())[:24]
            section.value(f"hard_{slug}_{key}_t_p95_mm", t.p95)
            section.value(f"hard_{slug}_{key}_r_p95_deg", r.p95)
            if family.goal and key in worst:
                worst[key] = (max(worst[key][0], t.p95), max(worst[key][1], r.p95))
    judged = [f.name for f in HARD_FAMILIES if f.goal]
    for key, (t95, r95) in worst.items():
        section.goals.append(
            Goal(
                f"hard scenes, {HARD_ROWS[key]}: p95 <= {GOAL_T_MM} mm and <= {GOAL_R_DEG}° on "
                f"each of {len(judged)} families ({'; '.join(judged)})",
                f"worst {fmt(t95)} mm, {fmt(r95)}°",
                t95 <= GOAL_T_MM and r95 <= GOAL_R_DEG,
            )
        )
    return table
