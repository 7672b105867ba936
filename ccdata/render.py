"""Offscreen rendering of the benchmark's three cameras with explicit, recorded settings, and
writing rendered frames as PNG and MP4 (`ccdata render`).

Meta-World renders with MuJoCo's defaults (4096 shadow map, 4x MSAA, reflections, skybox),
which costs ~100 ms per 64 px frame in software GL. The benchmark turns those off by default
(~6 ms per frame) and records the settings beside every dataset and run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from ccdata.errors import InputError

CAMERAS: tuple[str, ...] = ("topview", "frontview", "gripperPOV")
"""The benchmark's cameras, in channel-stacking order."""


MAX_IMAGE_SIZE = 16384
"""The largest offscreen framebuffer side every OpenGL 4.5 implementation must support
(GL_MAX_RENDERBUFFER_SIZE); beyond it MuJoCo's renderer fails with a page of EGL errors."""


@dataclass(frozen=True)
class RenderSettings:
    """How camera images are rendered. Defaults are the benchmark's (cheap, recorded)."""

    image_size: int = 64
    """Side of the square images in pixels."""
    shadows: bool = False
    """Cast shadows (MuJoCo default: on; ~10x the cost in software GL)."""
    reflections: bool = False
    """Reflective floor and walls (MuJoCo default: on)."""
    skybox: bool = False
    """Draw the skybox (MuJoCo default: on)."""
    msaa_samples: int = 0
    """Multisample anti-aliasing samples (MuJoCo default: 4)."""
    shadow_size: int = 4096
    """Shadow map resolution, used only when shadows are on."""

    def __post_init__(self) -> None:
        if not 8 <= self.image_size <= MAX_IMAGE_SIZE:
            raise InputError(f"image_size must be in [8, {MAX_IMAGE_SIZE}], got {self.image_size}")
        if self.msaa_samples < 0:
            raise InputError(f"msaa_samples must be >= 0, got {self.msaa_samples}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class MultiCameraRenderer:
    """One MuJoCo offscreen context that renders several named cameras of one model.

    One context per process: several contexts in one process can corrupt each other's frames.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        settings: RenderSettings,
        cameras: tuple[str, ...] = CAMERAS,
    ) -> None:
        size = settings.image_size
        model.vis.quality.offsamples = settings.msaa_samples
        model.vis.quality.shadowsize = settings.shadow_size
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, size)
        model.vis.global_.offheight = max(model.vis.global_.offheight, size)
        for name in cameras:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name) < 0:
                raise ValueError(f"camera {name!r} is not in the model")
        self.cameras = cameras
        self.settings = settings
        self._renderer = mujoco.Renderer(model, size, size)
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = settings.shadows
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = settings.reflections
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = settings.skybox

    def render(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        """Images (H, W, 3) uint8, upright, keyed by camera name."""
        images = {}
        for name in self.cameras:
            self._renderer.update_scene(data, camera=name)
            images[name] = self._renderer.render().copy()
        return images

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def write_png(path: Path, image) -> None:
    """An RGB uint8 (H, W, 3) image as PNG (OpenCV, which LeRobot installs), atomically."""
    import cv2

    ok, data = cv2.imencode(".png", image[..., ::-1])  # OpenCV orders channels BGR
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {image.shape} image as PNG")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.tobytes())
    tmp.replace(path)


def write_mp4(path: Path, frames, fps: int) -> None:
    """H.264 MP4 of (T, H, W, 3) uint8 frames, written to a temp file then renamed. PyAV, not
    OpenCV: OpenCV's wheels cannot encode H.264 (only MPEG-4 part 2)."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.mp4")
    with av.open(str(tmp), mode="w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames.shape[1] // 2 * 2, frames.shape[2] // 2 * 2
        stream.pix_fmt = "yuv420p"
        for image in frames:
            image = image[: stream.height, : stream.width]
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    tmp.replace(path)
