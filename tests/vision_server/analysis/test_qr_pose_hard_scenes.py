"""qr_pose on scenes harder than the bench's (issue 29 part 4): depth misregistered by (2, 1) px
and scaled by +0.5 %, on oblique views (30-45° off the code's normal), codes near the image
border, a code on a plate standing 8 cm off the wall behind it with a narrow margin, a
1280x720 D435-like stereo camera, depth with 10 % holes, and a lens with barrel distortion.
Rotation p95 <= 0.2° and translation p95 <= 0.5 mm on each family, without a sensor check
(nothing configured) and with its correction. On these views the code before issue 29 read
0.204° (unchecked) and 0.212° (checked) on the D435-like camera and 0.71 mm unchecked through
the distorted lens; after it, at most 0.166° and 0.19 mm."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from geometry import invert_transform, rotation_angle
from simulation.hard_scenes import HardFamily, hard_views
from vision_server.analysis import qr_pose

FloatArray = NDArray[np.float64]
SHIFT_PX = (2.0, 1.0)
SCALE_BIAS = 0.005
TEXT = "cellvision:station-1"
CHECKED: dict[str, Any] = {
    # what a sensor check leaves: its fit ~0.15 px off the true shift, with its standard errors
    "depth_scale": 1.0 + SCALE_BIAS,
    "depth_shift_px": (2.15, 0.9),
    "depth_scale_std": 1e-4,
    "depth_shift_std_px": (0.15, 0.11),
    "corner_bias_px": -0.03,
}
FAMILIES = (
    HardFamily("oblique", tilt_deg=(30.0, 45.0)),
    HardFamily("border", off_centre=0.85),
    HardFamily("plate", tilt_deg=(0.0, 40.0), margin_m=0.012, standoff_m=0.08),
    HardFamily(
        "d435",
        (0.6, 1.5),
        (0.0, 40.0),
        off_centre=0.5,
        size=(1280, 720),
        f_px=910.0,
        fb_px_m=0.05 * 910.0,
        sigma_d_px=0.08,
    ),
    HardFamily("holes", dropout=0.1),
    HardFamily("distortion", off_centre=0.6, dist=(-0.08, 0.05, 0.0004, -0.0003, 0.0)),
)


def _errors(
    family: HardFamily, views: int, frames: int
) -> dict[str, tuple[list[float], list[float]]]:
    out: dict[str, tuple[list[float], list[float]]] = {"unchecked": ([], []), "checked": ([], [])}
    drawn = hard_views(
        family,
        views,
        seed=29,
        frames=frames,
        shift_px=SHIFT_PX,
        scale_bias=SCALE_BIAS,
        text=TEXT,
    )
    for frame, depths, camera_from_qr in drawn:
        truth_inv = invert_transform(camera_from_qr)
        for label, kw in (("unchecked", {}), ("checked", CHECKED)):
            pose = qr_pose(
                frame.color,
                depths,
                frame.truth.intrinsics,
                expect=TEXT,
                side_m=0.16,
                **kw,
            )
            e = truth_inv @ pose.camera_from_qr
            out[label][0].append(float(np.linalg.norm(e[:3, 3])))
            out[label][1].append(float(np.degrees(rotation_angle(e[:3, :3]))))
    return out


@pytest.fixture(scope="module")
def hard_errors() -> dict[str, dict[str, tuple[list[float], list[float]]]]:
    """Per family and path: translation errors (m) and rotation errors (deg)."""
    return {
        family.name: _errors(family, 6 if family.size[0] > 640 else 8, 3) for family in FAMILIES
    }


@pytest.mark.parametrize("path", ["unchecked", "checked"])
@pytest.mark.parametrize("family", [f.name for f in FAMILIES])
def test_hard_scenes_meet_the_goal(hard_errors: dict[str, Any], family: str, path: str) -> None:
    # each kind of scene on its own (see the module's docstring for the figures before)
    t, r = hard_errors[family][path]
    assert len(t) == (6 if family == "d435" else 8)  # every view measured
    assert float(np.percentile(r, 95)) <= 0.2
    assert float(np.percentile(t, 95)) <= 0.0005
