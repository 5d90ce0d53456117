"""Calibration-board corners: a ChArUco board (OpenCV's aruco module) or a plain chessboard.

:func:`detect_board` returns the inner corners it found as :class:`BoardCorners`: sub-pixel
image positions ``(u, v)`` in full-image pixels, their ids and their positions on the board.

Board frame (OpenCV's): origin at the outer top-left corner of the printed board, x along the
columns (to the right on the print), y along the rows (down the print), z into the board,
metres. Inner corner ``id = row * (columns - 1) + column`` sits at
``((column + 1) * square_m, (row + 1) * square_m, 0)``.

A ChArUco board identifies each corner by the markers around it, so a partly seen or rotated
board still gives the right ids. A plain chessboard must be seen whole; its corner order is
OpenCV's, which for a board with the same parity of rows and columns may start from either
end: calibration does not care (each view is solved with its own pose), anything that needs
the board's own frame should use ChArUco.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import BadImageError, NotFoundError, RoiError

__all__ = ["BOARD_KINDS", "DICTIONARIES", "BoardCorners", "BoardSpec", "detect_board"]

FloatArray = NDArray[np.float64]
BOARD_KINDS = ("charuco", "chessboard")
DICTIONARIES: dict[str, int] = {
    name: int(getattr(cv2.aruco, name))
    for name in (
        "DICT_4X4_50",
        "DICT_4X4_100",
        "DICT_4X4_250",
        "DICT_5X5_100",
        "DICT_5X5_250",
        "DICT_6X6_250",
        "DICT_APRILTAG_36h11",
    )
}
MIN_CORNERS = 4  # fewer cannot constrain a view's pose


@dataclass(frozen=True)
class BoardSpec:
    """A printed board: ``columns`` x ``rows`` squares of ``square_m`` metres; for ChArUco the
    markers' side ``marker_m`` and their ``dictionary`` (a name of ``DICTIONARIES``)."""

    kind: str
    columns: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board kind must be one of {BOARD_KINDS}, got {self.kind!r}")
        if self.columns < 3 or self.rows < 3:
            raise ValueError(
                f"a board needs at least 3 x 3 squares, got {self.columns} x {self.rows}"
            )
        if not self.square_m > 0:
            raise ValueError(f"square_m must be positive, got {self.square_m}")
        if self.kind == "charuco":
            if not 0 < self.marker_m < self.square_m:
                raise ValueError(
                    f"marker_m must lie between 0 and square_m ({self.square_m}), "
                    f"got {self.marker_m}"
                )
            if self.dictionary not in DICTIONARIES:
                raise ValueError(
                    f"unknown dictionary {self.dictionary!r}; known: "
                    f"{', '.join(sorted(DICTIONARIES))}"
                )
            markers = (self.columns * self.rows) // 2
            size = int(
                cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary]).bytesList.shape[0]
            )
            if markers > size:
                raise ValueError(
                    f"a {self.columns} x {self.rows} ChArUco board needs {markers} markers; "
                    f"{self.dictionary} has {size}"
                )

    @property
    def corner_count(self) -> int:
        """How many inner corners the board has."""
        return (self.columns - 1) * (self.rows - 1)

    def object_points(self, ids: NDArray[np.int32]) -> FloatArray:
        """Board-frame positions (N, 3) in metres of the inner corners ``ids`` (N,)."""
        cols = self.columns - 1
        column, row = ids % cols, ids // cols
        return np.stack(
            [(column + 1) * self.square_m, (row + 1) * self.square_m, np.zeros(len(ids))],
            axis=1,
        ).astype(np.float64)

    @property
    def charuco(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board, made once per spec and kept outside it: the spec travels pickled
        to the process lane's workers, an OpenCV board cannot."""
        return _charuco_board(self)


@lru_cache(maxsize=16)
def _charuco_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARIES[spec.dictionary])
    return cv2.aruco.CharucoBoard(
        (spec.columns, spec.rows), spec.square_m, spec.marker_m, dictionary
    )


@dataclass(frozen=True)
class BoardCorners:
    """Inner corners found: ``uv`` (N, 2) full-image pixels, ``ids`` (N,) int, ``object_points``
    (N, 3) board frame, metres; ``markers``: ArUco markers decoded (0 for a chessboard)."""

    uv: FloatArray
    ids: NDArray[np.int32]
    object_points: FloatArray
    markers: int


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise BadImageError(
            f"expected a non-empty 8-bit gray or BGR image, got {image.dtype} {image.shape}"
        )
    if image.ndim == 3:
        if image.shape[2] != 3:
            raise BadImageError(f"expected 1 or 3 channels, got {image.shape[2]}")
        gray: NDArray[np.uint8] = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.uint8)
        return gray
    return image


def _charuco(
    gray: NDArray[np.uint8], board: BoardSpec
) -> tuple[FloatArray, NDArray[np.int32], int]:
    params = cv2.aruco.CharucoParameters()
    params.tryRefineMarkers = True
    detector_params = cv2.aruco.DetectorParameters()
    # Sub-pixel marker corners make the homography that first places the chessboard corners
    # better; the chessboard corners themselves are refined with cornerSubPix below.
    detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(board.charuco, params, detector_params)
    corners, ids, marker_corners, _ = detector.detectBoard(gray)
    markers = 0 if marker_corners is None else len(marker_corners)
    if corners is None or ids is None or len(ids) == 0:
        return np.empty((0, 2)), np.empty(0, np.int32), markers
    uv = corners.reshape(-1, 2).astype(np.float32)
    # The window reaches to just short of the markers (they sit (square - marker) / 2 from
    # the corner): their edges would pull the corner off; at least 2 px, at most 10 px.
    side = _square_px(uv, ids.reshape(-1).astype(np.int32), board)
    gap = side * (board.square_m - board.marker_m) / (2.0 * board.square_m)
    half = int(np.clip(np.floor(gap) - 1, 2, 10))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001)
    refined = cv2.cornerSubPix(gray, uv.reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int32), markers


def _square_px(uv: NDArray[np.float32], ids: NDArray[np.int32], board: BoardSpec) -> float:
    """The smallest distance in pixels between two detected corners that are neighbours on
    the board (a square's side, as seen where the board is most foreshortened)."""
    cols = board.columns - 1
    where = {int(i): k for k, i in enumerate(ids)}
    sides = [
        float(np.linalg.norm(uv[where[i + step]] - uv[k]))
        for i, k in where.items()
        for step in (1, cols)
        if i + step in where and (step == cols or (i % cols) + 1 < cols)
    ]
    return min(sides) if sides else 12.0


def _chessboard(gray: NDArray[np.uint8], board: BoardSpec) -> tuple[FloatArray, NDArray[np.int32]]:
    size = (board.columns - 1, board.rows - 1)
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCornersSB(gray, size, flags=flags)
    if not found or corners is None:
        return np.empty((0, 2)), np.empty(0, np.int32)
    uv = corners.reshape(-1, 2).astype(np.float64)
    return uv, np.arange(len(uv), dtype=np.int32)


def detect_board(
    image: NDArray[np.uint8],
    board: BoardSpec,
    *,
    roi: tuple[int, int, int, int] | None = None,
    min_corners: int = MIN_CORNERS,
) -> BoardCorners:
    """Find the inner corners of ``board`` in ``image`` (H, W) or (H, W, 3) uint8.

    ``roi``: ``(u, v, width, height)`` to search in (corners are still full-image pixels).
    Raises :class:`NotFoundError` when fewer than ``min_corners`` corners are found (the
    message says how many markers were seen), :class:`BadImageError` / :class:`RoiError`
    for unusable input.
    """
    gray = _gray(image)
    u0 = v0 = 0
    if roi is not None:
        u0, v0, w, h = roi
        if w <= 0 or h <= 0 or u0 < 0 or v0 < 0 or u0 + w > gray.shape[1] or v0 + h > gray.shape[0]:
            raise RoiError(
                f"ROI {roi} does not lie inside the {gray.shape[1]}x{gray.shape[0]} image"
            )
        gray = np.ascontiguousarray(gray[v0 : v0 + h, u0 : u0 + w])
    if board.kind == "charuco":
        uv, ids, markers = _charuco(gray, board)
    else:
        (uv, ids), markers = _chessboard(gray, board), 0
    if len(ids) < min_corners:
        seen = f" ({markers} ArUco markers decoded)" if board.kind == "charuco" else ""
        raise NotFoundError(
            f"{len(ids)} of the {board.corner_count} corners of the {board.columns}x{board.rows} "
            f"{board.kind} board found{seen}; at least {min_corners} are needed"
        )
    order = np.argsort(ids)
    uv, ids = uv[order] + np.array([u0, v0], dtype=np.float64), ids[order]
    return BoardCorners(uv, ids, board.object_points(ids), markers)
