"""``vision_pick``: find a part with the tool camera and pick it (the paper's section 2.3,
Table 1), and its future work: a taught polygonal search region.

Taught: ``p_cam_start`` and ``p_cam_end`` (tool poses: where the tool camera searches from,
looking down), ``h_detect`` (the height of the feature the vision system finds, e.g. the top of
a rotor cap), ``h_grasp`` (the TCP's height when grasping), the inspection's name and the step
length. Heights are z in the record's frame.

Execution along the line (Table 1): move the camera from start to end in steps of at most
``step_m``; at each stop capture, INSPECT (image in the request), undistort each returned pixel,
cast its ray, intersect the plane z = ``h_detect``, set z = ``h_grasp`` and project on the line
through the camera's start and end positions (at the grasp height); a part whose projection
lies between them is picked (else the search goes on). With several candidates, the one
nearest the tool is picked.

With a taught ``region`` (polygon x0, y0, x1, y1, ... in the record's frame) instead: camera
stations cover the polygon in a boustrophedon grid at the camera's footprint (with ``overlap``
and ``margin_m``), at the height and orientation of ``p_cam_start``, visited nearest first
(a nearest-neighbour tour from the tool's position); a part is accepted when its grasp point
lies inside the polygon.

``refine`` (beyond the paper, default 0): before grasping, look again from straight above the
chosen candidate (its image then sits at the image centre, where lens and perspective errors
are smallest) and use that measurement. In the simulated cell Table 1 alone is accurate to
~0.06 mm (p95) with the server's circle locator; a second look brings it to ~0.01 mm.

Failure reasons: ``not_found`` (searched everything, saw nothing), ``out_of_region`` (saw parts,
none in the acceptance region), ``grasp_failed`` (the gripper closed on nothing).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform

from ..devices import Camera, Unreachable
from ..vision_geometry import (
    AcceptanceSegment,
    Polygon,
    greedy_order,
    line_stations,
    optical_axis_hit,
    pixels_to_plane,
    plan_search_grid,
    tool_pose_viewing,
    view_footprint,
)
from .base import Args, Skill, SkillContext, SkillSpec, register_skill
from .basic import along_tool_z
from .conditions import Condition, GripperEmpty, Holding, Unmet
from .outcome import FailureReason, Outcome, fail
from .record import Param, ParamType

__all__ = ["Candidate", "NearSearchRegion", "VisionPick", "detect_on_plane"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Candidate:
    """One detection mapped to the robot: ``p_detect`` on the plane z = h_detect and
    ``p_grasp`` (z = h_grasp), both in the record's frame; ``uv`` the returned pixel; ``score``
    the server's."""

    p_detect: FloatArray
    p_grasp: FloatArray
    uv: tuple[float, float]
    score: float


def detect_on_plane(
    ctx: SkillContext, camera: Camera, inspection: str, h_detect: float, h_grasp: float
) -> tuple[list[Candidate], dict[str, Any]]:
    """Capture, INSPECT (the image in the request) and map every returned feature to the
    robot's active frame: Table 1, steps 2-3 and 5-8. Returns the candidates (best first, as
    the server sorts them) and a summary of the inspection."""
    cap = camera.capture()
    result = ctx.vision.inspect(inspection, cap.color)
    data = dict(result.data)
    features = [f for f in data.get("features") or [] if "u" in f and "v" in f]
    summary = {"passed": bool(result.passed), "count": len(features)}
    if not features:
        return [], summary
    uv = np.array([[float(f["u"]), float(f["v"])] for f in features])
    points = pixels_to_plane(cap.intrinsics, cap.user_from_camera, uv, h_detect)
    out = []
    for f, p in zip(features, points, strict=True):
        if not np.all(np.isfinite(p)):
            continue
        grasp = p.copy()
        grasp[2] = h_grasp
        out.append(Candidate(p, grasp, (float(f["u"]), float(f["v"])), float(f.get("score", 0))))
    return out, summary


@dataclass(frozen=True)
class NearSearchRegion(Condition):
    """The tool is within ``tolerance_m`` (horizontally) of the taught search: the start-end
    segment, or the polygon when a region is taught."""

    tolerance_m: float = 0.3
    name: str = "near_search_region"

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        tool = ctx.world.tool_pose_in(args.record.frame)[:3, 3]
        region = args["region"]
        if region:
            distance = Polygon.from_flat(region).distance(tool[:2])
            what = "search region"
        else:
            start = args.pose("p_cam_start")[:3, 3]
            end_pose = args["p_cam_end"]
            end = start if end_pose is None else end_pose[:3, 3]
            seg = AcceptanceSegment(start * [1, 1, 0], end * [1, 1, 0])
            t = float(np.clip(seg.parameter(tool * [1, 1, 0]), 0.0, seg.length))
            distance = float(np.linalg.norm(tool[:2] - (seg.start + t * seg.direction)[:2]))
            what = "search line p_cam_start-p_cam_end"
        if distance <= self.tolerance_m:
            return None
        return Unmet(
            self.name,
            FailureReason.NOT_NEAR,
            f"the tool is {distance:.3f} m from the taught {what} (frame "
            f"{args.record.frame!r}), more than the {self.tolerance_m:g} m allowed; move the "
            f"robot there first",
        )

    def describe(self) -> str:
        return f"the tool is within {self.tolerance_m:g} m of the taught search line or region"


def _xyz(p: FloatArray) -> list[float]:
    return [round(float(v), 6) for v in p[:3]]


@register_skill
class VisionPick(Skill):
    spec = SkillSpec(
        name="vision_pick",
        doc="search for a part with the tool camera along a taught line (or over a taught "
        "region) and pick it (paper, Table 1)",
        params=(
            Param(
                "p_cam_start",
                ParamType.POSE,
                "tool pose where the search starts, the tool camera looking down at the parts",
                "m, rad",
            ),
            Param(
                "p_cam_end",
                ParamType.POSE,
                "tool pose where the search ends (required without a region)",
                "m, rad",
                default=None,
            ),
            Param("h_detect", ParamType.FLOAT, "height of the detected feature (z)", "m"),
            Param("h_grasp", ParamType.FLOAT, "height of the TCP when grasping (z)", "m"),
            Param(
                "inspection", ParamType.STR, "the server's locate inspection", default="cap_locate"
            ),
            Param("camera", ParamType.STR, "the robot's tool camera", default="tool_camera"),
            Param(
                "step_m",
                ParamType.FLOAT,
                "longest step between two captures along the line",
                "m",
                default=0.05,
                minimum=0.001,
                maximum=2.0,
            ),
            Param(
                "region",
                ParamType.FLOATS,
                "search polygon x0, y0, x1, y1, ... (none: search along the line)",
                "m",
                default=None,
            ),
            Param(
                "overlap",
                ParamType.FLOAT,
                "overlap of neighbouring views when covering a region",
                "",
                default=0.2,
                minimum=0.0,
                maximum=0.9,
            ),
            Param(
                "margin_m",
                ParamType.FLOAT,
                "parts nearer than this to a view's edge are left to the next view (region)",
                "m",
                default=0.025,
                minimum=0.0,
                maximum=0.5,
            ),
            Param(
                "max_lateral_m",
                ParamType.FLOAT,
                "also reject parts farther than this from the line (none: any)",
                "m",
                default=None,
                minimum=0.0,
            ),
            Param(
                "refine",
                ParamType.INT,
                "looks from straight above the candidate before grasping (0: Table 1 exactly)",
                "",
                default=0,
                minimum=0,
                maximum=3,
            ),
            Param(
                "approach_m",
                ParamType.FLOAT,
                "distance back along the tool's z to approach the grasp from",
                "m",
                default=0.08,
                minimum=0.0,
                maximum=0.5,
            ),
            Param(
                "speed_m_s",
                ParamType.FLOAT,
                "linear speed (none: the robot's default)",
                "m/s",
                default=None,
                minimum=1e-4,
                maximum=2.0,
            ),
        ),
        pre=(GripperEmpty(), NearSearchRegion()),
        post=(Holding(),),
    )

    # --- helpers ------------------------------------------------------------------------
    @staticmethod
    def _speed(args: Args) -> float | None:
        value = args["speed_m_s"]
        return None if value is None else float(value)

    @staticmethod
    def _tool_from_camera(camera: Camera) -> FloatArray:
        tfc = camera.tool_from_camera
        if tfc is None:
            fail(FailureReason.BAD_RECORD, "vision_pick needs a camera on the tool")
        return tfc

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        camera = ctx.camera(args.text("camera"))
        tfc = self._tool_from_camera(camera)
        h_detect, h_grasp = args.number("h_detect"), args.number("h_grasp")
        start = args.pose("p_cam_start")
        region_values = args["region"]
        stations: list[FloatArray]
        accept: Any
        if region_values:
            try:
                polygon = Polygon.from_flat(region_values)
                footprint = view_footprint(camera.intrinsics, start @ tfc, h_detect)
                grid = plan_search_grid(
                    polygon,
                    footprint,
                    overlap=args.number("overlap"),
                    margin_m=args.number("margin_m"),
                )
            except ValueError as exc:
                fail(FailureReason.BAD_RECORD, f"search region: {exc}")
            here = optical_axis_hit(ctx.robot.base_from_tool() @ tfc, h_detect)
            origin = ctx.robot.base_from_tool()[:2, 3] if here is None else here[:2]
            order = greedy_order(grid, origin)
            stations = [tool_pose_viewing(start, tfc, h_detect, grid[i]) for i in order]

            def accept(c: Candidate) -> bool:
                return polygon.contains(c.p_grasp[:2])

            mode = "region"
        else:
            end = args["p_cam_end"]
            if end is None:
                fail(FailureReason.BAD_RECORD, "give p_cam_end (the line's end) or a region")
            stations = line_stations(start, end, args.number("step_m"))
            # the camera's start and end positions, brought down to the grasp height (so the
            # lateral distance is horizontal; the projection is the paper's step 9)
            ends = [(pose @ tfc)[:3, 3] * [1, 1, 0] + [0, 0, h_grasp] for pose in (start, end)]
            segment = AcceptanceSegment(ends[0], ends[1])
            max_lateral = args["max_lateral_m"]

            def accept(c: Candidate) -> bool:
                return segment.contains(
                    c.p_grasp, max_lateral_m=None if max_lateral is None else float(max_lateral)
                )

            mode = "line"

        speed = self._speed(args)
        inspection = args.text("inspection")
        seen, rejected = 0, []
        for index, station in enumerate(stations):
            ctx.report(
                f"searching: view {index + 1} of {len(stations)}", index / max(1, len(stations))
            )
            ctx.robot.move_linear(station, speed_m_s=speed)
            candidates, _ = detect_on_plane(ctx, camera, inspection, h_detect, h_grasp)
            seen += len(candidates)
            accepted = [c for c in candidates if accept(c)]
            rejected += [c for c in candidates if not accept(c)]
            if not accepted:
                continue
            tool_xy = ctx.robot.base_from_tool()[:2, 3]
            chosen = min(accepted, key=lambda c: float(np.linalg.norm(c.p_grasp[:2] - tool_xy)))
            first = chosen
            looks = 0
            for _ in range(args.integer("refine")):
                better = self._refine(ctx, camera, args, station, tfc, chosen)
                if better is None:
                    break
                chosen, looks = better, looks + 1
            if not accept(chosen):
                rejected.append(chosen)
                continue
            return self._grasp(
                args,
                ctx,
                station,
                chosen,
                {
                    "mode": mode,
                    "view": index,
                    "views": len(stations),
                    "seen": seen,
                    "refined_looks": looks,
                    "first_estimate_xyz": _xyz(first.p_grasp),
                    "uv": [round(v, 3) for v in chosen.uv],
                },
            )
        data = {
            "mode": mode,
            "views": len(stations),
            "seen": seen,
            "rejected_xyz": [_xyz(c.p_grasp) for c in rejected[:10]],
        }
        if seen:
            fail(
                FailureReason.OUT_OF_REGION,
                f"saw {seen} part(s) in {len(stations)} views, none in the acceptance {mode}",
                data,
            )
        fail(
            FailureReason.NOT_FOUND,
            f"inspection {inspection!r} found nothing in {len(stations)} views",
            data,
        )

    def _refine(
        self,
        ctx: SkillContext,
        camera: Camera,
        args: Args,
        station: FloatArray,
        tfc: FloatArray,
        chosen: Candidate,
    ) -> Candidate | None:
        """Look from straight above ``chosen``; the nearest detection there (within 2 cm)."""
        h_detect, h_grasp = args.number("h_detect"), args.number("h_grasp")
        view = tool_pose_viewing(station, tfc, h_detect, chosen.p_detect[:2])
        try:
            ctx.robot.move_linear(view, speed_m_s=self._speed(args))
        except Unreachable:
            return None
        candidates, _ = detect_on_plane(ctx, camera, args.text("inspection"), h_detect, h_grasp)
        if not candidates:
            return None
        best = min(candidates, key=lambda c: float(np.linalg.norm(c.p_detect - chosen.p_detect)))
        if float(np.linalg.norm(best.p_detect - chosen.p_detect)) > 0.02:
            return None
        return best

    def _grasp(
        self,
        args: Args,
        ctx: SkillContext,
        station: FloatArray,
        chosen: Candidate,
        data: dict[str, Any],
    ) -> Outcome:
        speed = self._speed(args)
        grasp = make_transform(station[:3, :3], chosen.p_grasp)
        above = along_tool_z(grasp, -args.number("approach_m"))
        ctx.report(f"picking at {_xyz(chosen.p_grasp)}", 0.9)
        ctx.robot.move_linear(above, speed_m_s=speed)
        ctx.robot.move_linear(grasp, speed_m_s=speed)
        held = ctx.gripper.close()
        data = {**data, "grasp_xyz": _xyz(chosen.p_grasp), "frame": args.record.frame}
        if not held:
            ctx.gripper.open()
            ctx.robot.move_linear(above, speed_m_s=speed)
            fail(
                FailureReason.GRASP_FAILED,
                f"the gripper closed on nothing at {_xyz(chosen.p_grasp)} ({args.record.frame})",
                data,
            )
        part = getattr(ctx.gripper, "held_part", None)
        ctx.world.held_part = str(part) if part else "part"
        ctx.robot.move_linear(above, speed_m_s=speed)
        ctx.report("picked", 1.0)
        return Outcome.success({**data, "part": ctx.world.held_part})
