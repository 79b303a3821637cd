"""Video recording of ``riskflow_v0`` episodes: MP4 (imageio-ffmpeg) or GIF (pillow).

:class:`VideoRecorder` keeps its own off-screen :class:`~riskflow_env.render.SceneRenderer`
(so the env needs no ``render_mode``) and captures one frame after ``reset`` and one after
every ``step``. The file suffix picks the format. A path with an ``{episode}`` field gets
one file per episode; a plain path gets every recorded episode, back to back. MP4 frames
are streamed to ffmpeg as they come; GIF frames are held by pillow until the file closes
(at episode end, or at ``close()`` for a plain path).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pettingzoo.utils import BaseParallelWrapper

from riskflow_env.config import is_number, plain_number
from riskflow_env.folder_lock import check_output_folder, file_path, make_output_file
from riskflow_env.render import RenderConfig, SceneRenderer
from riskflow_env.wrappers.event_log import require_riskflow_env

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi")
SUFFIXES = (".gif", *VIDEO_SUFFIXES)


def check_video_path(path: str | os.PathLike, option: str = "path") -> Path:
    """``path`` as a video file to write: a suffix of :data:`SUFFIXES`, not a folder, in a
    folder that can be made; otherwise a ValueError naming ``option``."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"{option} must end in one of {SUFFIXES}, got {str(path)!r}")
    if path.is_dir():
        raise ValueError(f"{option}: {path} is a folder, not a video file")
    check_output_folder(path.parent, option)
    return path


class FrameWriter:
    """Appends (H, W, 3) uint8 frames to one video file; the format comes from the suffix.

    Args:
        path: output file; ``.gif`` or one of :data:`VIDEO_SUFFIXES`.
        fps: frames per second [1/s], > 0.
    """

    def __init__(self, path: str | os.PathLike, fps: float) -> None:
        self.path = check_video_path(path)
        suffix = self.path.suffix.lower()
        fps = check_fps(fps)
        make_output_file(self.path, in_place=True)  # ffmpeg and pillow write it in place
        self.frames = 0
        self._gif = suffix == ".gif"
        self._duration_ms = 1000.0 / fps
        if self._gif:
            import imageio.v3 as iio

            self._writer = iio.imopen(self.path, "w", plugin="pillow")
        else:
            try:
                import imageio_ffmpeg  # noqa: F401  (imageio's ffmpeg backend)
            except ImportError as error:
                raise ImportError(
                    f"writing {suffix} needs imageio-ffmpeg: pip install imageio-ffmpeg"
                ) from error
            import imageio.v2 as iio2

            # macro_block_size=2: any even frame size is encoded as is (yuv420p needs even).
            self._writer = iio2.get_writer(self.path, format="FFMPEG", fps=fps, macro_block_size=2)

    def append(self, frame: np.ndarray) -> None:
        """Add one (H, W, 3) uint8 frame."""
        try:
            if self._gif:
                self._writer.write(frame, duration=self._duration_ms, loop=0)
            else:
                self._writer.append_data(frame)
        except OSError as err:  # ffmpeg cannot write the file: a broken pipe
            raise self._failed(err) from None
        self.frames += 1

    def close(self) -> None:
        """Finish the file (idempotent)."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.close()
            except OSError as err:  # pillow writes a GIF only now
                raise self._failed(err) from None

    def _failed(self, err: OSError) -> OSError:
        return OSError(f"cannot write the video {self.path}: {err.strerror or err}")


def check_fps(fps: object) -> float:
    """``fps`` as a float; a ValueError unless it is a finite number > 0 (not a bool)."""
    if not (is_number(fps) and math.isfinite(plain_number(fps)) and plain_number(fps) > 0):
        raise ValueError(f"fps must be a finite number > 0 [frames/s], got {fps!r}")
    return float(plain_number(fps))


class VideoRecorder(BaseParallelWrapper):
    """Records ``riskflow_v0`` episodes to MP4 or GIF.

    Args:
        env: the env, or a wrapper of it (its ``unwrapped`` must be a RiskFlow env).
        path: output file, e.g. ``"videos/episode_{episode:03d}.mp4"`` (one file per
            episode) or ``"run.gif"`` (every recorded episode in one file).
        fps: frames per second; default ``env.metadata["render_fps"]`` (real time).
        config: view of the recorder's renderer (size, metres shown, trails).
        episode_trigger: which episode indices (0, 1, ...) to record; default all.

    Attributes:
        renderer: the recorder's :class:`SceneRenderer`; push overlays (plans,
            highlighted agents) to it with ``set_overlay``.
        paths: files written or being written, in order.
    """

    def __init__(
        self,
        env: Any,
        path: str | os.PathLike = "videos/episode_{episode:03d}.mp4",
        fps: float | None = None,
        config: RenderConfig | None = None,
        episode_trigger: Callable[[int], bool] | None = None,
    ) -> None:
        require_riskflow_env(env, "VideoRecorder")
        super().__init__(env)
        self.path_template = str(check_video_path(file_path(path)))
        try:  # the only field a path may hold is {episode}
            first = self.path_template.format(episode=0)
        except (KeyError, IndexError, ValueError, AttributeError, TypeError) as err:
            raise ValueError(
                f"path may hold one field, {{episode}} (e.g. {{episode:03d}}), got "
                f"{self.path_template!r} ({type(err).__name__}: {err})"
            ) from None
        check_output_folder(Path(first).parent, "path")
        self.per_episode = first != self.path_template.format(episode=1)
        self.fps = check_fps(fps if fps is not None else env.metadata.get("render_fps", 10))
        if episode_trigger is not None and not callable(episode_trigger):
            raise ValueError(
                "episode_trigger must be a function of the episode index that returns a bool "
                f"(e.g. lambda episode: episode % 10 == 0), got {episode_trigger!r}"
            )
        self.renderer = SceneRenderer("rgb_array", config)
        self.episode_trigger = episode_trigger or (lambda episode: True)
        self.paths: list[Path] = []
        self.episode = -1
        self._writer: FrameWriter | None = None
        self._recording = False

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if self.per_episode:
            self._close_writer()
        result = self.env.reset(seed=seed, options=options)
        self.episode += 1
        self._recording = bool(self.episode_trigger(self.episode))
        if self._recording:
            base = self.env.unwrapped
            self.renderer.reset(base)
            self._capture(base)
        return result

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        result = self.env.step(actions)
        if self._recording:
            base = self.env.unwrapped
            self.renderer.record(base)
            self._capture(base)
            if not base.agents and self.per_episode:
                self._close_writer()
        return result

    def close(self) -> None:
        """Finish the open file, then close the renderer and the env."""
        self._close_writer()
        self.renderer.close()
        self.env.close()

    def __enter__(self) -> VideoRecorder:
        return self

    def __exit__(self, exc_type: Any, exc: Any, traceback: Any) -> None:
        self.close()

    def _capture(self, base: Any) -> None:
        if self._writer is None:
            path = Path(self.path_template.format(episode=self.episode))
            self._writer = FrameWriter(path, self.fps)
            self.paths.append(path)
        self._writer.append(self.renderer.render(base))

    def _close_writer(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
