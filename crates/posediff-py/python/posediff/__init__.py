"""posediff: camera poses (and sparse points) from a handful of photos or a few hundred frames.

Without a checkpoint the cameras come from posediff's global structure-from-motion mapper;
with ``weights`` (an official PoseDiffusion checkpoint) from the diffusion model with
geometry-guided sampling. Cameras speak OpenCV: ``x_cam = R @ x_world + t``, pixels::

    import posediff
    rec = posediff.estimate("scene/images")            # a folder, paths, or HxWx3 uint8 arrays
    for cam in rec.cameras:
        print(cam.name, cam.K, cam.R, cam.t)
    rec.write("scene/out")                             # cameras.json, COLMAP, nerfstudio, PyTorch3D

The computation runs in Rust with the GIL released. Errors are ``FileNotFoundError`` (a
missing path), ``ValueError`` (a wrong input or option) or ``posediff.Error`` (an estimation
that failed), each with posediff's message.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Dict, Optional, Sequence, TypedDict, Union

from . import _native
from ._native import (
    Camera,
    Error,
    Reconstruction,
    __version__,
    opencv_to_pytorch3d,
    pose_encoding_to_cameras,
    pytorch3d_to_opencv,
    read_cameras,
    read_image,
    score,
)

__all__ = [
    "Camera",
    "Error",
    "EstimateOptions",
    "Estimator",
    "Reconstruction",
    "__version__",
    "estimate",
    "opencv_to_pytorch3d",
    "pose_encoding_to_cameras",
    "pytorch3d_to_opencv",
    "read_cameras",
    "read_image",
    "score",
]

if TYPE_CHECKING:
    from os import PathLike

    import numpy as np
    import numpy.typing as npt
    from typing_extensions import Unpack

ProgressCallback = Callable[[str, int, int, bool], Any]


class EstimateOptions(TypedDict, total=False):
    """The keyword options of :func:`estimate` and :meth:`Estimator.estimate` (the CLI's flags)."""

    config: "Union[str, PathLike[str]]"
    options: Dict[str, Any]
    focal_px: float
    intrinsics: "Union[str, PathLike[str], npt.NDArray[np.float64]]"
    init: "Union[str, PathLike[str]]"
    start_step: int
    refine: str
    matcher: str
    weights_dir: "Union[str, PathLike[str]]"
    pairs: str
    samples: int
    seed: int
    ggs: bool
    skip_bad_images: bool
    names: Sequence[str]
    masks: "Union[str, PathLike[str]]"
    database: "Union[str, PathLike[str]]"
    shard: str
    import_from: "Sequence[Union[str, PathLike[str]]]"
    fps: float
    max_frames: int


class _Bars:
    """tqdm bars, one per stage (``callback(stage, done, total, finished)``)."""

    def __init__(self, tqdm: Any) -> None:
        self._tqdm = tqdm
        self._bar: Any = None

    def __call__(self, stage: str, done: int, total: int, finished: bool) -> None:
        if finished:
            if self._bar is not None:
                self._bar.close()
                self._bar = None
            return
        if done == 0:
            if self._bar is not None:
                self._bar.close()
            self._bar = self._tqdm(total=total or None, desc=stage, leave=False)
        elif self._bar is not None:
            self._bar.update(1)


def _progress(progress: Union[bool, ProgressCallback, None]) -> Optional[ProgressCallback]:
    if progress is None or progress is False:
        return None
    if callable(progress):
        return progress
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return _Bars(tqdm)


def estimate(images: Any, *, weights: Any = None, device: str = "cpu",
             progress: Union[bool, ProgressCallback, None] = True,
             **options: Unpack[EstimateOptions]) -> Reconstruction:
    """Cameras (and points) for ``images``.

    ``images``: a folder (its .png/.jpg/.jpeg files, sorted), a list of image paths (in that
    order), a list of HxWx3 uint8 RGB arrays (named by ``names``, default ``image_000.png``,
    ...), or a video path or list of video paths (.mp4, .mov, .mkv, .avi, ...: each decoded
    once, its keyframes chosen and named ``<video>_f<frame>_t<seconds>s.jpg``; ``fps`` frames
    looked at per second, ``max_frames`` keyframes per video at most; ``masks`` then holds
    ``<frame index>.png`` per frame; ``rec.write(out)`` copies the keyframes to
    ``out/images``). ``weights``: an official PoseDiffusion checkpoint; without it the mapper estimates the
    cameras. Options, as the CLI's flags: ``focal_px``, ``intrinsics`` (a cameras.json path or
    an (N, 3, 3) array), ``init`` (``"geometric"`` or a cameras.json), ``start_step``,
    ``refine`` (``"converge"``, ``"bundle"``, ``"official"``, ``"none"``), ``matcher``
    (``"sift"``, ``"orb"``, ``"aliked-lightglue"``, ``"aliked-n16rot-lightglue"``,
    ``"disk-lightglue"``), ``weights_dir`` (the learned matcher's
    weights, from ``cargo xtask weights``), ``pairs`` (``"auto"``, ``"exhaustive"``, ``"sequential:K"``,
    ``"retrieval:K"``), ``samples``, ``seed``, ``ggs``, ``device`` (``"cpu"``, ``"cuda"``),
    ``skip_bad_images``, ``masks`` (a folder of COLMAP-named masks, ``<image name>.png``, zero =
    ignore), ``database`` (COLMAP's database.db: features and matches read from it first and
    written to it as they are made, as the CLI's ``--database``), ``import_from`` (workers'
    databases whose features and pairs ``database`` lacks, as ``--from``; see
    :mod:`posediff.distributed`); the pipeline's options tree (run.json's ``options``) from ``config``
    (a TOML or JSON file, the CLI's ``--config``) and ``options`` (``{"orientation.strong_pair":
    100}``, the CLI's ``--set``). ``progress``: ``True`` for tqdm bars when tqdm is installed, ``False``,
    or a callable ``(stage, done, total, finished)``.
    """
    return _native.estimate(images, dict(options), weights=weights, device=device,
                            progress=_progress(progress))


class Estimator:
    """A PoseDiffusion checkpoint loaded once for many calls::

        est = posediff.Estimator("posediffusion.pth")
        for folder in folders:
            est.estimate(folder, seed=0).write(folder + "/out")
    """

    def __init__(self, weights: Any, *, device: str = "cpu") -> None:
        self._native = _native.Estimator(weights, device=device)

    def estimate(self, images: Any, *, progress: Union[bool, ProgressCallback, None] = True,
                 **options: Unpack[EstimateOptions]) -> Reconstruction:
        """As :func:`posediff.estimate` with this checkpoint."""
        return self._native.estimate(images, dict(options), progress=_progress(progress))

    def __repr__(self) -> str:
        return repr(self._native)
