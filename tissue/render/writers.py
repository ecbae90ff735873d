"""Image and animation writers: PNG frames, GIF (Pillow) and MP4 (imageio-ffmpeg).

Frames are numpy arrays (h, w, 3) or (h, w, 4) uint8. GIFs are committed to git, so they are
downscaled, capped in frame count and share one palette (smaller files, no palette flicker).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import TissueError


def write_png(path, image: np.ndarray) -> Path:
    """Write one frame as PNG (RGBA keeps its alpha), creating the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image)).save(path, optimize=True)
    return path


def flatten(image: np.ndarray, background=(255, 255, 255)) -> np.ndarray:
    """RGB version of a frame, compositing an alpha channel over `background` (GIF, MP4 have none)."""
    if image.shape[-1] == 3:
        return image
    alpha = image[..., 3:].astype(np.float32) / 255.0
    rgb = image[..., :3] * alpha + np.asarray(background, np.float32) * (1.0 - alpha)
    return np.round(rgb).astype(np.uint8)


class GifWriter:
    """Collects downscaled frames and writes them at `close()`.

    At most `max_frames` frames are kept, evenly spread over the sequence; the frame duration is
    stretched accordingly so the GIF lasts as long as the simulation it shows. (Pillow merges
    identical consecutive frames into one longer frame.)

    palette: "shared" (one octree palette for all frames: the smallest files) or "per-frame" (a
    median-cut palette per frame: smooth colour-map gradients on shaded surfaces, where a shared
    palette leaves blotches, at about twice the size).
    """

    def __init__(self, path, fps: float = 20.0, width: int | None = 480, max_frames: int = 120,
                 colors: int = 255, palette: str = "shared"):
        if palette not in ("shared", "per-frame"):
            raise TissueError(f"{path}: GIF palette must be 'shared' or 'per-frame', got {palette!r}")
        self.path, self.fps, self.width = Path(path), fps, width
        self.max_frames, self.colors, self.palette = max_frames, colors, palette
        self._frames: list[Image.Image] = []

    def append(self, image: np.ndarray) -> None:
        frame = Image.fromarray(flatten(image))
        if self.width and frame.width > self.width:
            height = max(1, round(frame.height * self.width / frame.width))
            frame = frame.resize((self.width, height), Image.Resampling.LANCZOS)
        self._frames.append(frame)

    def close(self) -> Path | None:
        if not self._frames:
            warnings.warn(f"{self.path}: no frames were written, GIF not created", stacklevel=2)
            return None
        frames = self._frames
        step = 1
        if len(frames) > self.max_frames:
            step = len(frames) / self.max_frames
            frames = [frames[int(i * step)] for i in range(self.max_frames)]
        if self.palette == "per-frame":
            indexed = [f.quantize(colors=self.colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
                       for f in frames]
        else:
            # One palette for all frames, built from a strip of five frames spread over the sequence.
            # Octree without dithering gave the smoothest shared colour maps and the smallest files
            # (a shared median cut bands visibly; Floyd-Steinberg doubles the size and adds noise).
            samples = [frames[round(i * (len(frames) - 1) / 4)] for i in range(5)]
            strip = Image.new("RGB", (samples[0].width, samples[0].height * len(samples)))
            for i, s in enumerate(samples):
                strip.paste(s, (0, i * s.height))
            palette = strip.quantize(colors=self.colors, method=Image.Quantize.FASTOCTREE)
            indexed = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        duration = max(20, round(1000.0 * step / self.fps))  # ms; browsers clamp < 20 ms
        indexed[0].save(self.path, save_all=True, append_images=indexed[1:], duration=duration,
                        loop=0, optimize=True, disposal=1)
        self._frames = []
        return self.path


class Mp4Writer:
    """Streams full-size frames to ffmpeg (H.264, yuv420p: plays everywhere).

    Needs the `imageio-ffmpeg` wheel (it ships its own ffmpeg); without it the MP4 is skipped with
    a warning rather than failing the simulation that produces it.
    """

    def __init__(self, path, fps: float = 20.0, quality: float = 7.0):
        self.path, self.fps, self.quality = Path(path), fps, quality
        self._gen = None
        self.skipped = False
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            self.skipped = True
            warnings.warn(f"{self.path}: MP4 skipped, imageio-ffmpeg is not installed "
                          "(pip install imageio-ffmpeg, or tissue[render])", stacklevel=3)

    def append(self, image: np.ndarray) -> None:
        if self.skipped:
            return
        frame = flatten(image)
        # yuv420p needs even sizes; crop one pixel rather than rescale.
        frame = np.ascontiguousarray(frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2])
        if self._gen is None:
            import imageio_ffmpeg

            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._size = (frame.shape[1], frame.shape[0])
            self._gen = imageio_ffmpeg.write_frames(
                str(self.path), self._size, fps=self.fps, codec="libx264", pix_fmt_out="yuv420p",
                quality=self.quality, macro_block_size=1, ffmpeg_log_level="error")
            self._gen.send(None)  # start ffmpeg
        elif (frame.shape[1], frame.shape[0]) != self._size:
            raise TissueError(f"{self.path}: frame size changed from {self._size} to "
                              f"{(frame.shape[1], frame.shape[0])}")
        self._gen.send(frame)

    def close(self) -> Path | None:
        if self._gen is None:
            if not self.skipped:
                warnings.warn(f"{self.path}: no frames were written, MP4 not created", stacklevel=2)
            return None
        self._gen.close()
        self._gen = None
        return self.path


def writer_for(path, fps: float, **gif_options):
    """The writer for a file name: .gif or .mp4."""
    suffix = Path(path).suffix.lower()
    if suffix == ".gif":
        return GifWriter(path, fps=fps, **gif_options)
    if suffix in (".mp4", ".m4v"):
        return Mp4Writer(path, fps=fps)
    raise TissueError(f"render: cannot write an animation to {path}; use a .gif or .mp4 name")
