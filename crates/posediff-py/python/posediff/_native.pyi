"""Type stubs of the extension module (see posediff/__init__.py for the public API)."""

from os import PathLike
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike[str]]
_Images = Union[_Path, Sequence[_Path], Sequence[npt.NDArray[np.uint8]]]
_Progress = Optional[Callable[[str, int, int, bool], Any]]

__version__: str

class Error(Exception): ...

class Camera:
    @property
    def name(self) -> str: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def estimated(self) -> bool: ...
    @property
    def reason(self) -> Optional[str]: ...
    @property
    def K(self) -> Optional[npt.NDArray[np.float64]]: ...
    @property
    def R(self) -> Optional[npt.NDArray[np.float64]]: ...
    @property
    def t(self) -> Optional[npt.NDArray[np.float64]]: ...
    @property
    def center(self) -> Optional[npt.NDArray[np.float64]]: ...

class Reconstruction:
    @property
    def cameras(self) -> list[Camera]: ...
    @property
    def points(self) -> Optional[dict[str, npt.NDArray[Any]]]: ...
    @property
    def report(self) -> dict[str, Any]: ...
    def write(
        self,
        out: _Path,
        formats: Optional[Sequence[str]] = None,
        *,
        colmap_format: str = "text",
        images: Optional[str] = None,
    ) -> dict[str, Any]: ...
    def __len__(self) -> int: ...

class Estimator:
    def __init__(self, weights: _Path, *, device: str = "cpu") -> None: ...
    def estimate(
        self, images: _Images, options: Optional[dict[str, Any]] = None, progress: _Progress = None
    ) -> Reconstruction: ...

def estimate(
    images: _Images,
    options: Optional[dict[str, Any]] = None,
    weights: Optional[_Path] = None,
    device: str = "cpu",
    progress: _Progress = None,
) -> Reconstruction: ...
def read_cameras(path: _Path) -> list[Camera]: ...
def check_options(options: Optional[dict[str, Any]] = ...) -> None: ...
def run_stages(
    images: Union[_Path, Sequence[_Path]],
    stop: str,
    options: Optional[dict[str, Any]] = ...,
    progress: Optional[Callable[[str, int, int, bool], Any]] = ...,
) -> dict[str, Any]: ...
def read_image(path: _Path) -> npt.NDArray[np.uint8]: ...
def score(pred: Union[Reconstruction, _Path], gt: _Path) -> dict[str, Any]: ...
def opencv_to_pytorch3d(
    K: npt.NDArray[np.float64],
    R: npt.NDArray[np.float64],
    t: npt.NDArray[np.float64],
    image_size: tuple[int, int],
) -> dict[str, npt.NDArray[np.float64]]: ...
def pytorch3d_to_opencv(
    R: npt.NDArray[np.float64],
    T: npt.NDArray[np.float64],
    focal_length: npt.NDArray[np.float64],
    principal_point: npt.NDArray[np.float64],
    image_size: tuple[int, int],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def pose_encoding_to_cameras(
    encoding: npt.NDArray[np.float64], image_size: tuple[int, int]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
