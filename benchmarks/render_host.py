"""Host work the render stage adds to each frame, outside the path tracer, on one CPU thread.

What a frame and a clip cost on the host after Mitsuba hands the frame back,
each timed alone (best of 5 repeats) on a real frame of a synthetic waving sheet
(render.synthetic) at ``--resolution``:

* ``finish``: composite over the background, camera effects, tone map to 8-bit
  sRGB (``ClipRenderer.finish``);
* ``png``, ``exr``: writing the frame as PNG (``ldr/``) and as float32 EXR (``hdr/``);
* ``frames_npy``: writing the clip's ``frames.npy`` (``--frames`` frames), per clip;
* ``clip_setup``: a new clip's ClipRenderer (texture, lights, camera draws) and
  its procedural background, per clip.

``per_frame`` adds them up per frame for each output set the stage can write
(``npy``: the ``paper`` preset; ``png``; ``png+exr``: what every clip wrote
before ``frames.npy``), clip costs spread over ``--frames`` frames. On a GPU
these run beside the renderer (writer threads) but hold Python's GIL for most of
their time, so they bound a process's frame rate. Writes a JSON under
benchmarks/results/ with the command line.

    python benchmarks/render_host.py --resolution 112 --frames 40
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.render_throughput import run_record, save_report  # noqa: E402
from render.backend import load_mitsuba  # noqa: E402


def best_ms(fn, repeats: int = 5, number: int = 20) -> float:
    """The fastest of ``repeats`` mean times of ``number`` calls, in milliseconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for i in range(number):
            fn(i)
        times.append((time.perf_counter() - start) / number)
    return round(1e3 * min(times), 3)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=112)
    p.add_argument("--frames", type=int, default=40, help="frames per clip (spreads the per-clip costs)")
    p.add_argument("--variant", default="paper")
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    mi = load_mitsuba("scalar_rgb")   # renders the one HDR frame the timings start from; not timed

    from PIL import Image

    from render.exr import write_exr
    try:
        from render.frames import write_frames
    except ImportError:             # a checkout from before frames.npy: its finish, PNG and EXR alone
        write_frames = None
    from render.scene import ClipRenderer
    from render.synthetic import waving_sheet
    from render.variants import get_variant

    variant = get_variant(args.variant)
    clip = waving_sheet(frames=args.frames, n=33)

    def renderer(index: int) -> ClipRenderer:
        return ClipRenderer(clip, variant, resolution=args.resolution, spp=1, run_seed=0, clip_index=index,
                            backend=mi.variant())

    r = renderer(0)
    hdr = r.render_hdr(0)
    ldr = r.finish(hdr, 0)
    clip_frames = np.repeat(ldr[None], args.frames, axis=0)
    with tempfile.TemporaryDirectory(prefix="render-host-") as tmp:
        folder = Path(tmp)
        ms = {
            "finish": best_ms(lambda i: r.finish(hdr, i % args.frames)),
            "png": best_ms(lambda i: Image.fromarray(ldr).save(folder / f"{i}.png")),
            "exr": best_ms(lambda i: write_exr(folder / f"{i}.exr", hdr)),
            "clip_setup": best_ms(lambda i: renderer(1000 + i).background, number=5),
        }
        if write_frames is not None:
            ms["frames_npy"] = best_ms(lambda i: write_frames(folder, clip_frames), number=5)
    per_clip = (ms.get("frames_npy", 0.0) + ms["clip_setup"]) / args.frames
    per_frame = {"npy": ms["finish"] + per_clip}
    per_frame["png"] = per_frame["npy"] + ms["png"]
    per_frame["png+exr"] = per_frame["png"] + ms["exr"]
    report = {
        **run_record(argv), "settings": {"resolution": args.resolution, "frames": args.frames, "variant": args.variant},
        "ms": ms, "per_frame_ms": {k: round(v, 3) for k, v in per_frame.items()},
    }
    print(json.dumps(report, indent=2))
    return save_report(report, args.out, f"render_host-{args.resolution}")


if __name__ == "__main__":
    main()
