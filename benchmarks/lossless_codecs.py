"""Lossless codecs for the demo's video: CPU per frame, bytes per frame, bit-exact decode.

Run: ``./dev python benchmarks/lossless_codecs.py`` (a few minutes). Writes the section
"Lossless video codecs" of ``docs/performance.md`` (other sections are left alone) and
prints it. ``--quick`` encodes a few frames in two rounds and writes nothing unless
``--out`` is given (what CI runs: that it still runs, no timings judged).

What runs, in one process: the frames the demo stores (``configs/demo.yaml``: the
simulator's ``configs/scenes/demo_grade3.yaml``, 640x480 BGR, every frame of the scene's
125 s; of them the distinct pictures, as the recorder encodes only those: a repeated
read-only picture is muxed as the previous frame's packet), cut to the gray bounding box of
the ROI as ``storage.video_roi_only`` stores them (the daemon's ROI, crop, then
``to_gray``), evenly subsampled to ``--frames``. Each candidate encodes every frame with
one FFmpeg thread, every frame intra (as a session video is stored: any frame decodes
alone), through PyAV as the recorder does (``VideoFrame.from_ndarray``, ``encode``); its
CPU time is ``time.process_time`` around that loop (the process runs nothing else
meanwhile), per frame. The candidates run in rounds, in an order rotated from round to
round (a drift of the machine weighs on all alike); each candidate's figure is the median
of its rounds, with their smallest and largest. Its ratio to the session video's FFV1
(:data:`REFERENCE`) is the median of the rounds' ratios; it is reported only when
the rounds' ratios agree within :data:`MARGIN` of it (interquartile range over median), as
the choice between codecs is judged at that margin: a machine whose load moves more than
that between rounds makes the table say so instead of giving a ratio. Bytes per frame are
the packets' sizes. Every packet is decoded again with PyAV (one thread) and compared with
the frame it was made of, array for array: "bit-exact" is that comparison for every frame,
not a property claimed of the codec; the decode's CPU per frame is given too.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._doc import write_section  # noqa: E402
from benchmarks._machine import cpu_model  # noqa: E402
from stipi_daemon.storage.video import FFV1_OPTIONS  # noqa: E402

DOC = ROOT / "docs" / "performance.md"
SECTION = "## Lossless video codecs"
SCENE = ROOT / "configs" / "scenes" / "demo_grade3.yaml"
#: Judging margin of a ratio [-]: a ratio whose rounds' interquartile range exceeds this
#: fraction of their median is not reported.
MARGIN = 0.10
#: The candidate every ratio is taken against: the session video's FFV1 as the recorder
#: encodes it (``storage.video.FFV1_OPTIONS``).
REFERENCE = "FFV1 as recorded (`FFV1_OPTIONS`: {})".format(
    ", ".join(f"{k} {v}" for k, v in FFV1_OPTIONS.items())
)
#: Decoded layouts whose first plane is 8-bit luma (or gray) [-].
EIGHT_BIT = frozenset({"gray", "yuv420p", "yuv422p", "yuv444p", "yuvj420p"})
#: Decoder of an encoder whose name differs.
DECODERS = {"libx264": "h264"}
Image = np.ndarray[Any, np.dtype[np.uint8]]


@dataclass(frozen=True)
class Candidate:
    """One codec with its settings: FFmpeg encoder name, pixel format, codec options, and
    whether it encodes the whole gray frame instead of the ROI's box."""

    label: str
    codec: str
    pix_fmt: str
    options: dict[str, str] = field(default_factory=dict)
    whole_frame: bool = False


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(REFERENCE, "ffv1", "gray", dict(FFV1_OPTIONS)),
    Candidate("FFV1 level 3, slicecrc 0", "ffv1", "gray", {"level": "3", "slicecrc": "0"}),
    Candidate(
        "FFV1 level 3, slicecrc 0, Golomb-Rice coder",
        "ffv1",
        "gray",
        {"level": "3", "slicecrc": "0", "coder": "0"},
    ),
    Candidate(
        "FFV1 level 1 (Golomb-Rice coder, small context)",
        "ffv1",
        "gray",
        {"level": "1", "coder": "0", "context": "0"},
    ),
    Candidate("FFV1 level 1, range coder", "ffv1", "gray", {"level": "1", "coder": "1"}),
    Candidate("FFV1 level 1, large context", "ffv1", "gray", {"level": "1", "context": "1"}),
    Candidate("FFV1 as recorded, whole frame", "ffv1", "gray", dict(FFV1_OPTIONS), True),
    Candidate("FFV1 level 1, whole frame", "ffv1", "gray", {"level": "1"}, whole_frame=True),
    Candidate("FFVHuff, left prediction", "ffvhuff", "gray", {"pred": "left"}),
    Candidate("FFVHuff, median prediction", "ffvhuff", "gray", {"pred": "median"}),
    Candidate("FFVHuff, adaptive tables", "ffvhuff", "gray", {"context": "1"}),
    Candidate("MagicYUV, left prediction", "magicyuv", "gray", {"pred": "left"}),
    Candidate("MagicYUV, median prediction", "magicyuv", "gray", {"pred": "median"}),
    Candidate("MagicYUV, gradient prediction", "magicyuv", "gray", {"pred": "gradient"}),
    Candidate("Ut Video (yuv420p, chroma 128)", "utvideo", "yuv420p"),
    Candidate("HuffYUV (yuv422p, chroma 128)", "huffyuv", "yuv422p"),
    Candidate("PNG, zlib level 1", "png", "gray", {"compression_level": "1"}),
    Candidate("JPEG-LS", "jpegls", "gray"),
    Candidate(
        "x264 lossless (qp 0, ultrafast, intra)",
        "libx264",
        "gray",
        {"qp": "0", "preset": "ultrafast", "x264-params": "keyint=1:threads=1"},
    ),
    Candidate(
        "x264 lossless (qp 0, ultrafast, intra), CABAC",
        "libx264",
        "gray",
        {"qp": "0", "preset": "ultrafast", "x264-params": "keyint=1:threads=1:cabac=1"},
    ),
    Candidate("raw (rawvideo, no compression)", "rawvideo", "gray"),
)


def demo_frames(count: int, *, every: int = 1) -> tuple[list[Image], list[Image], int]:
    """``count`` distinct pictures of the demo (evenly spread over its distinct ones), as
    the ROI's gray box and as the whole gray frame; ``every`` > 1 looks only at every
    ``every``-th frame of the scene (``--quick``); and how many distinct pictures there
    are (of those looked at)."""
    from stipi_daemon.analysis.imaging import FrameProcessor, to_gray
    from stipi_daemon.sim.pipeline import Pipeline
    from stipi_daemon.sim.scene import load_scene

    scene = load_scene(SCENE)
    pipe = Pipeline(scene)
    fps = scene.camera.fps
    distinct: list[int] = []  # frame numbers of the distinct pictures (none kept: memory)
    last: object = None
    for frame in pipe.frames():
        if frame.pixels is last:  # a repeated read-only picture: the recorder sends a copy
            continue
        last = frame.pixels
        if frame.index % every == 0:
            distinct.append(frame.index)
    picks = np.linspace(0, len(distinct) - 1, min(count, len(distinct))).round().astype(int)
    images = [
        np.asarray(next(iter(pipe.frames(distinct[i] / fps, distinct[i] / fps))).image)
        for i in picks
    ]
    fp = FrameProcessor(images[0].shape, scene.probe.threshold, pipe.renderer.roi)
    y0, y1, x0, x1 = fp.bounding_box
    boxes = [np.ascontiguousarray(to_gray(im[y0:y1, x0:x1])) for im in images]
    wholes = [np.ascontiguousarray(to_gray(im)) for im in images]
    return boxes, wholes, len(distinct)


def _encoder(c: Candidate, size: tuple[int, int]) -> Any:
    import av

    ctx: Any = av.CodecContext.create(c.codec, "w")
    ctx.width, ctx.height = size
    ctx.pix_fmt = c.pix_fmt
    ctx.time_base = Fraction(1, 1000)
    ctx.gop_size = 1
    ctx.thread_count = 1
    ctx.options = dict(c.options)
    ctx.open()
    return ctx


def _frame(c: Candidate, image: Image) -> Any:
    """The PyAV frame of a gray picture for ``c``: gray as it is, a YUV layout with the
    picture as its luma and neutral chroma."""
    import av

    if c.pix_fmt == "gray":
        return av.VideoFrame.from_ndarray(image, format="gray")
    h, w = image.shape
    frame = av.VideoFrame(w, h, c.pix_fmt)
    planes = frame.planes
    _plane_view(planes[0], h, w)[:] = image
    for p in planes[1:]:
        _plane_view(p, p.height, p.width)[:] = 128
    return frame


def _plane_view(plane: Any, h: int, w: int) -> Image:
    """A plane's pixels as an ``(h, w)`` array view (its line size may exceed ``w``)."""
    buf = np.frombuffer(memoryview(plane), np.uint8)
    return buf.reshape(-1, plane.line_size)[:h, :w]


def encode_all(c: Candidate, images: list[Image]) -> tuple[float, list[bytes], tuple[bytes, str]]:
    """CPU seconds (process) to encode ``images`` one frame each, their payloads and what
    a decoder needs of the encoder: its configuration record (extradata) and FourCC (Ut
    Video tells its layout by it)."""
    h, w = images[0].shape
    ctx = _encoder(c, (w, h))
    payloads: list[bytes] = []
    t0 = time.process_time()
    for i, image in enumerate(images):
        frame = _frame(c, image)
        frame.pts = i
        payloads.extend(bytes(p) for p in ctx.encode(frame))
    payloads.extend(bytes(p) for p in ctx.encode(None))
    cpu = time.process_time() - t0
    return cpu, payloads, (bytes(ctx.extradata or b""), str(ctx.codec_tag or ""))


def decode_all(
    c: Candidate, payloads: list[bytes], setup: tuple[bytes, str], images: list[Image]
) -> tuple[float, int]:
    """CPU seconds to decode every payload (one decoder over the stream, as the session
    video is read back; one thread), and how many pictures equal the frames they were made
    of: gray, or a YUV layout whose luma is the frame and chroma 128."""
    import av

    ctx: Any = av.CodecContext.create(DECODERS.get(c.codec, c.codec), "r")
    extradata, tag = setup
    if extradata:
        ctx.extradata = extradata
    if tag:
        ctx.codec_tag = tag
    h, w = images[0].shape
    ctx.width, ctx.height = w, h
    if c.codec == "rawvideo":
        ctx.pix_fmt = c.pix_fmt
    ctx.thread_count = 1
    ctx.thread_type = "NONE"
    pictures: list[Any] = []
    t0 = time.process_time()
    for payload in payloads:
        pictures.extend(ctx.decode(av.Packet(payload)))
    pictures.extend(ctx.decode(None))
    cpu = time.process_time() - t0
    same = 0
    for picture, image in zip(pictures, images, strict=False):
        planes = picture.planes
        luma = _plane_view(planes[0], h, w)
        chroma_ok = all(bool((_plane_view(p, p.height, p.width) == 128).all()) for p in planes[1:])
        eight_bit = picture.format.name in EIGHT_BIT
        if eight_bit and np.array_equal(luma, image) and chroma_ok:
            same += 1
    return cpu, same if len(pictures) == len(images) else min(same, len(pictures))


def matroska_round_trip(c: Candidate, images: list[Image]) -> tuple[bool, int]:
    """Whether PyAV lets a Matroska file hold ``c`` (as a session video is opened), and if
    so how many of ``images`` the project's readback
    (:func:`~stipi_daemon.storage.video_readback.iter_video_images`) gives back equal, from
    a file muxed as the recorder muxes (a cluster per frame, its CRC-32, flushed)."""
    import tempfile

    import av

    from stipi_daemon.storage.video import MUXER_OPTIONS, PTS_TIME_BASE
    from stipi_daemon.storage.video_readback import TAG_IMAGE, iter_video_images

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "video.mkv"
        container = av.open(str(path), "w", format="matroska", options=dict(MUXER_OPTIONS))
        try:
            stream: Any = container.add_stream(c.codec, options=dict(c.options))
        except ValueError:  # "'matroska' format does not support ... codec"
            container.close()
            return False, 0
        h, w = images[0].shape
        ctx = stream.codec_context
        ctx.pix_fmt, ctx.gop_size, ctx.thread_count = c.pix_fmt, 1, 1
        ctx.width, ctx.height = w, h
        ctx.time_base = stream.time_base = PTS_TIME_BASE
        container.metadata[TAG_IMAGE] = "gray"
        for i, image in enumerate(images):
            frame = _frame(c, image)
            frame.pts, frame.time_base = 17 * i, PTS_TIME_BASE
            for pkt in stream.encode(frame):
                container.mux(pkt)
        for pkt in stream.encode(None):
            container.mux(pkt)
        container.close()
        back = list(iter_video_images(path))
    same = sum(np.array_equal(a, b) for a, b in zip(back, images, strict=False))
    return True, same


@dataclass
class Result:
    """A candidate's figures over the rounds."""

    cpu_ms: list[float] = field(default_factory=list)  # encode, per frame, each round
    bytes_per_frame: float = 0.0
    decode_ms: float = 0.0
    exact: int = 0
    frames: int = 0
    matroska: bool = False
    readback_exact: int = 0
    error: str | None = None


def run(rounds: int, boxes: list[Image], wholes: list[Image]) -> dict[str, Result]:
    """Every candidate in ``rounds`` rounds, the order rotated from round to round."""
    results = {c.label: Result() for c in CANDIDATES}
    order = list(CANDIDATES)
    for r in range(rounds):
        k = r % len(order)
        for c in order[k:] + order[:k]:
            res = results[c.label]
            if res.error is not None:
                continue
            images = wholes if c.whole_frame else boxes
            try:
                cpu, payloads, setup = encode_all(c, images)
                if r == 0:
                    dec, res.exact = decode_all(c, payloads, setup, images)
                    res.matroska, res.readback_exact = matroska_round_trip(c, images)
            except Exception as exc:  # a codec this FFmpeg lacks or refuses: said
                res.error = f"{type(exc).__name__}: {exc}"
                continue
            res.cpu_ms.append(cpu / len(images) * 1e3)
            if r == 0:
                res.bytes_per_frame = sum(len(p) for p in payloads) / len(images)
                res.decode_ms = dec / len(images) * 1e3
                res.frames = len(images)
    return results


def ratio(res: Result, ref: Result) -> tuple[float, float, float, float]:
    """Median of the rounds' CPU ratios to ``ref``, its smallest, largest, and the
    interquartile range over the median."""
    rs = [a / b for a, b in zip(res.cpu_ms, ref.cpu_ms, strict=False)]
    med = statistics.median(rs)
    if len(rs) >= 2:
        q = statistics.quantiles(rs, n=4, method="inclusive")
        iqr = (q[2] - q[0]) / med
    else:
        iqr = float("inf")
    return med, min(rs), max(rs), iqr


def render(
    results: dict[str, Result], rounds: int, box: tuple[int, int], load: str, distinct: int
) -> str:
    ref = results[REFERENCE]
    lines = [
        SECTION,
        "",
        "Issue 43: the demo's lossless video at the cost of the pipeline, decoded "
        "bit-exactly. Command: `./dev python benchmarks/lossless_codecs.py` (one process; "
        f"{ref.frames} of the demo's {distinct:,} distinct pictures, spread over its 125 s "
        "(the recorder encodes only those; a repeat is muxed as the packet before), the "
        "ROI's gray "
        f"box {box[0]}x{box[1]} px as `video_roi_only` stores it, or the whole 640x480 gray "
        f"frame where said; {rounds} rounds in a rotated order; CPU = `time.process_time` "
        "of the encode loop, one FFmpeg thread, every frame intra; the ratio is the median "
        "of the rounds' ratios to the recorder's FFV1, given only when their interquartile "
        f"range is within {100 * MARGIN:.0f} % of it; decode: PyAV, one thread, every "
        "picture compared with its frame).",
        "",
        f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; "
        f"load average (1, 5, 15 min) {load} (a shared machine: CPU time, not wall time).",
        "",
        "| codec, settings | encode CPU per frame [ms] (median; rounds' min-max) "
        "| ratio to the recorder's FFV1 (rounds' min-max) | bytes per frame | decode CPU per "
        "frame [ms] | bit-exact decode (PyAV) | in Matroska through PyAV, read back by "
        "`iter_video_images` |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    for c in CANDIDATES:
        res = results[c.label]
        if res.error is not None or not res.cpu_ms:
            lines.append(f"| {c.label} | not run: {res.error} | | | | | |")
            continue
        med = statistics.median(res.cpu_ms)
        r, lo, hi, iqr = ratio(res, ref)
        cell = (
            f"{r:.2f}x ({lo:.2f}-{hi:.2f})"
            if iqr <= MARGIN
            else f"not given: rounds disagree by {100 * iqr:.0f} % > {100 * MARGIN:.0f} %"
        )
        exact = (
            f"yes, {res.exact} of {res.frames}"
            if res.exact == res.frames
            else f"**NO**, {res.exact} of {res.frames}"
        )
        mkv = (
            "refused (not a Matroska codec at FFmpeg's normal compliance)"
            if not res.matroska
            else (
                f"yes, {res.readback_exact} of {res.frames} equal"
                if res.readback_exact == res.frames
                else f"**NOT equal**: {res.readback_exact} of {res.frames}"
            )
        )
        lines.append(
            f"| {c.label} | {med:.3f} ({min(res.cpu_ms):.3f}-{max(res.cpu_ms):.3f}) | {cell} "
            f"| {res.bytes_per_frame:,.0f} | {res.decode_ms:.3f} | {exact} | {mkv} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--frames", type=int, default=160, help="distinct pictures encoded")
    parser.add_argument("--rounds", type=int, default=9, help="rounds over every candidate")
    parser.add_argument("--quick", action="store_true", help="8 pictures, 2 rounds")
    parser.add_argument("--out", type=Path, help="write the section into this file")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args(argv)
    frames, rounds, every = args.frames, args.rounds, 1
    if args.quick:
        frames, rounds, every = 8, 2, 30
    boxes, wholes, distinct = demo_frames(frames, every=every)
    results = run(rounds, boxes, wholes)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    h, w = boxes[0].shape
    text = render(results, rounds, (w, h), load, distinct)
    print(text)
    out = args.out if args.out is not None else (None if args.quick else DOC)
    if out is not None and not args.no_write:
        write_section(out, SECTION, text, after="## Demo speed")
    bad = [c.label for c in CANDIDATES if results[c.label].exact != results[c.label].frames]
    if results[REFERENCE].exact != results[REFERENCE].frames:
        sys.exit(f"the reference FFV1 does not decode bit-exactly: {bad}")


if __name__ == "__main__":
    main()
