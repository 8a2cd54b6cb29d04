"""Texture sets of one relief in three colourings, and how well an
enlargement's map finds their own place (scripts/height-signature.sh).

  height_signature.py make DIR       DIR/{A,B,C}: texture sets (docs/texture-set.md)
  height_signature.py score MAT...   own-place shares of enlarged materials

A: a random relief (slopes ≈ 0.33 RMS, bumps of 0.5 and 1.2 mm) under
blotches of colour, Lambert + GGX (F0 0.04, roughness 0.55), 80 mm tiles
of 1024 px, the 25.4 mm sample cut at (30, 22) mm. B: the same with its
albedo multiplied by one smooth grey factor (0.53-1.88x, faded or dyed
darker in places). C: the same with each channel's own smooth factor
(0.31-3.2x: another dye). Seeded: the same sets on every run.
"""
import json
import os
import struct
import sys
import zlib

import numpy as np

N, SIZE, OFFSET, SAMPLE = 1024, 80.0, (30.0, 22.0), 25.4


def sets(root):
    rng = np.random.default_rng(58)
    mm = SIZE / N
    y, x = np.mgrid[0:N, 0:N] * mm  # rows along v, columns along u, mm

    def smooth(scale_mm, k=60):
        # Random Fourier modes periodic over the tile, RMS ≈ 1.
        f = np.zeros((N, N))
        for _ in range(k):
            fx, fy = rng.normal(0, 1 / scale_mm, 2)
            nx, ny = np.round(fx * SIZE), np.round(fy * SIZE)
            f += np.cos(2 * np.pi * (nx * x + ny * y) / SIZE + rng.uniform(0, 2 * np.pi))
        return f / np.sqrt(k / 2)

    h = 0.04 * smooth(1.2) + 0.015 * smooth(0.5)
    gy, gx = np.gradient(h, mm)
    n = np.stack([-gx, -gy, np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    base = np.stack([0.35 + 0.12 * smooth(2.0) + 0.05 * smooth(0.7) for _ in range(3)], -1)
    base = np.clip(base, 0.05, 0.9)
    grey = np.exp(0.2 * smooth(15.0, 12))[..., None]
    dyes = np.stack([np.exp(0.35 * smooth(15.0, 12)) for _ in range(3)], -1)
    print(f"slope RMS {np.sqrt((gx ** 2 + gy ** 2).mean()):.3f}; grey factor "
          f"{grey.min():.2f}-{grey.max():.2f}; per-channel {dyes.min():.2f}-{dyes.max():.2f}")
    for name, diffuse in [("A", base), ("B", base * grey), ("C", base * dyes)]:
        d = os.path.join(root, name)
        os.makedirs(d, exist_ok=True)
        with open(os.path.join(d, "material.toml"), "w") as f:
            f.write(f'format = 1\nname = "relief-{name}"\nsize_mm = {SIZE}\n'
                    f'sample_offset_mm = [{OFFSET[0]}, {OFFSET[1]}]\n')
        png16(os.path.join(d, "diffuse.png"), srgb(np.clip(diffuse, 0, 1)))
        png16(os.path.join(d, "specular.png"), srgb(np.full((N, N, 3), 0.04)))
        png16(os.path.join(d, "roughness.png"), np.full((N, N), 0.55))
        png16(os.path.join(d, "normal.png"), (n + 1) / 2)


def srgb(v):
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def png16(path, img):
    """A 16-bit grey or RGB PNG (zlib only: no imaging library needed)."""
    a = (np.clip(img, 0, 1) * 65535 + 0.5).astype(">u2")
    h, w = a.shape[:2]
    colour = 2 if a.ndim == 3 else 0

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    raw = b"".join(b"\x00" + a[r].tobytes() for r in range(h))
    with open(path + ".tmp", "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n"
                + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, colour, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    os.replace(path + ".tmp", path)


def score(paths):
    from safetensors import safe_open
    from safetensors.numpy import load_file
    for path in paths:
        m = load_file(path)["enlargement"].astype(np.float64)
        with safe_open(path, "numpy") as f:
            extent = json.loads(f.metadata()["material"])["extent_mm"]
        rows, cols = m.shape[:2]
        r, c = np.mgrid[0:rows, 0:cols]
        p = np.stack([(c + 0.5) / cols * extent[0], (r + 0.5) / rows * extent[1]], -1)
        own = (p - np.array(OFFSET)) / SAMPLE
        # The window the sample was cut from, 1 mm in from its edges.
        inside = np.all((own > 1 / SAMPLE) & (own < 1 - 1 / SAMPLE), -1)
        err = np.linalg.norm((m + 0.5) / 65536 - own, axis=-1)[inside] * SAMPLE
        print(f"{path}: own place (within 0.5 mm) {np.mean(err < 0.5):.3f} of "
              f"{inside.sum()} texels in the window; median distance {np.median(err):.2f} mm")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "make":
        sets(sys.argv[2])
    elif len(sys.argv) >= 3 and sys.argv[1] == "score":
        score(sys.argv[2:])
    else:
        sys.exit(__doc__)
