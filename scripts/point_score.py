"""The 12 × 12-point score of a built material against the simulator's
ground truth, as docs/benchmarks.md's tables since session 99 give it
("Texture sets of other kinds"), and where its error lies.

  point_score.py MATERIAL TRUTH [--area]

MATERIAL: a material file (`scanner build` / `scanner demo`); TRUTH: what
`hil-sim truth --material` takes for the sample it was scanned from (a
library name or a texture-set directory). Runs `target/release/scanner`
and `target/release/hil-sim` (override with $SCANNER and $HILSIM); build
them first (`cargo build --release -p host -p hil-sim`). Needs numpy (the
repository's .venv has it).

- captured: 12 × 12 uv points ((i + ½) / 12) of every (light, view) pair
  of the material's own calibrated directions;
- novel: 300 random pairs, wi and wo each uniform in solid angle within
  θ ≤ 60° (numpy's default_rng(7)), each at 144 random uv points;
- PSNR with the peak at the 99th percentile of the truth's values.

With --area, a quarter of the captured pairs again against the truth
averaged over each material texel (4 × 4 points, then looked up
bilinearly at the point as the material looks its texels up), at the
material's S and at the detail layer's 2S: the score a perfect estimate
at that resolution would get (the "limit"), and the material's against
it. The material is never read for anything but its directions and
resolution (the safetensors header).
"""
import json
import os
import struct
import subprocess
import sys
import tempfile

import numpy as np


def header(path):
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        return json.loads(json.loads(f.read(n))["__metadata__"]["material"])


def answers(tool, args, queries, tmp, tag):
    q, out = os.path.join(tmp, tag + "-q.npy"), os.path.join(tmp, tag + "-a.npy")
    np.save(q, queries.astype(np.float32))
    run = subprocess.run([tool, *args(q, out)], capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"{tool} failed ({run.returncode}): {run.stderr.strip()}")
    return np.load(out)


def psnr(truth, other, peak):
    return 10 * np.log10(peak**2 / np.mean((truth - other) ** 2))


def grid_queries(lights, views):
    g = (np.arange(12) + 0.5) / 12
    uu, vv = np.meshgrid(g, g, indexing="ij")
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    rows = [np.hstack([uv, np.tile(l, (144, 1)), np.tile(v, (144, 1))]) for l in lights for v in views]
    return np.vstack(rows)


def novel_queries():
    rng = np.random.default_rng(7)

    def dirs(k):
        ct = 1 - rng.random(k) * (1 - np.cos(np.radians(60)))
        ph = rng.random(k) * 2 * np.pi
        st = np.sqrt(1 - ct * ct)
        return np.stack([st * np.cos(ph), st * np.sin(ph), ct], 1)

    wi, wo = dirs(300), dirs(300)
    rows = []
    for i in range(300):
        u = rng.random((144, 2))
        rows.append(np.hstack([u, np.tile(wi[i], (144, 1)), np.tile(wo[i], (144, 1))]))
    return np.vstack(rows)


def texel_area(q, size, truth):
    """The truth averaged over each of the four texels (of `size`²) around
    each query's uv, looked up bilinearly between their centres."""
    x = q[:, :2] * size - 0.5
    x0 = np.floor(x)
    t = x - x0
    off = (np.arange(4) + 0.5) / 4 / size
    ou, ov = np.meshgrid(off, off, indexing="ij")
    sub = np.stack([ou.ravel(), ov.ravel()], 1)
    total = 0
    for du in (0, 1):
        for dv in (0, 1):
            corner = np.stack([np.clip(x0[:, 0] + du, 0, size - 1), np.clip(x0[:, 1] + dv, 0, size - 1)], 1)
            rows = np.repeat(q, 16, 0)
            rows[:, :2] = np.repeat(corner / size, 16, 0) + np.tile(sub, (len(q), 1))
            mean = truth(rows).reshape(len(q), 16, 3).mean(1)
            w = (t[:, 0] if du else 1 - t[:, 0]) * (t[:, 1] if dv else 1 - t[:, 1])
            total = total + mean * w[:, None]
    return total


def main():
    args = [a for a in sys.argv[1:] if a != "--area"]
    if len(args) != 2:
        sys.exit(__doc__)
    material, source = args
    if not os.path.isfile(material):
        sys.exit(f"{material}: no such material file")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    scanner = os.environ.get("SCANNER", os.path.join(root, "target/release/scanner"))
    hilsim = os.environ.get("HILSIM", os.path.join(root, "target/release/hil-sim"))
    meta = header(material)
    lights = np.array([m["direction"] for m in meta["lights"]])
    views = np.array([m["direction"] for m in meta["views"]])
    with tempfile.TemporaryDirectory() as tmp:
        count = iter(range(1 << 30))

        def truth(q):
            return answers(hilsim, lambda i, o: ["truth", "--material", source, "--queries", i, "-o", o], q, tmp, f"t{next(count)}")

        def shade(q):
            return answers(scanner, lambda i, o: ["shade", material, "--queries", i, "-o", o], q, tmp, f"m{next(count)}")

        line = []
        for name, q in [("captured", grid_queries(lights, views)), ("novel", novel_queries())]:
            t, m = truth(q), shade(q)
            line.append(f"{name} {psnr(t, m, np.percentile(t, 99)):.2f} dB")
        print(f"{material}: " + ", ".join(line))
        if "--area" in sys.argv:
            q = grid_queries(lights, views)[np.repeat(np.arange(len(lights) * len(views)) % 4 == 0, 144)]
            t, m = truth(q), shade(q)
            peak = np.percentile(t, 99)
            s = meta["resolution"]
            parts = [f"quarter of the captured pairs: material {psnr(t, m, peak):.2f} dB"]
            for size in (s, 2 * s):
                a = texel_area(q, size, truth)
                parts.append(f"{size}² texel-area limit {psnr(t, a, peak):.2f} dB, material against it {psnr(a, m, peak):.2f} dB")
            print("  " + "; ".join(parts))


if __name__ == "__main__":
    main()
