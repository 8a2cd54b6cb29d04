#!/usr/bin/env python3
"""Shade a material file from docs/material-format.md alone.

A second implementation of the file's shading, written from the document
and nothing else, with numpy and safetensors (what a third party has). The
test `python_reads_the_material_file_from_the_spec` (host/tests/python.rs)
runs it on materials of every kind and compares its answers with
`scanner shade`'s: where they differ, the document or the reader is wrong.

    shade_from_spec.py MATERIAL QUERIES.npy ANSWERS.npy

QUERIES.npy: (N, 8) u, v, wi, wo (docs/query-format.md); ANSWERS.npy:
(N, 3) float32, f · cos θi.
"""

import hashlib
import json
import struct
import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


def unit(d):
    return d / np.linalg.norm(d)


class Triangles:
    """Spherical barycentric weights ("Default interpolation")."""

    def __init__(self, dirs, tris):
        self.dirs = dirs
        self.tris = tris.astype(np.int64)
        # M = [a b c] as columns; w = M⁻¹ d.
        self.inv = np.linalg.inv(np.transpose(dirs[self.tris], (0, 2, 1)))
        uses = {}
        for t in self.tris:
            for k in range(3):
                e = (min(t[k], t[(k + 1) % 3]), max(t[k], t[(k + 1) % 3]))
                uses[e] = uses.get(e, 0) + 1
        # The boundary: arcs of one triangle only.
        self.arcs = [e for e, n in uses.items() if n == 1]

    def weights(self, d):
        w = self.inv @ d
        inside = np.all(w >= -1e-6, axis=1)
        if inside.any():
            t = int(np.argmax(inside))
            w = w[t].copy()
            w[w < 1e-5] = 0.0
            return list(zip(self.tris[t], w / w.sum()))
        # Outside every triangle: the nearest point of the boundary, on an
        # arc (its projection on the arc's great circle, if within the arc)
        # or at a vertex. Nearest = largest cosine.
        best = (-2.0, None)
        for i, j in self.arcs:
            a, b = self.dirs[i], self.dirs[j]
            for k in (i, j):
                if d @ self.dirs[k] > best[0]:
                    best = (d @ self.dirs[k], [(k, 1.0)])
            n = unit(np.cross(a, b))
            if d @ np.cross(n, a) >= 0 and d @ np.cross(b, n) >= 0:
                p = d - (d @ n) * n
                # p = α a + β b
                g = np.array([[a @ a, a @ b], [a @ b, b @ b]])
                al, be = np.maximum(np.linalg.solve(g, np.array([a @ p, b @ p])), 0.0)
                if np.linalg.norm(p) > best[0] and al + be > 0:
                    best = (np.linalg.norm(p), [(i, al / (al + be)), (j, be / (al + be))])
        return best[1]


class Cells:
    """The patent's table ("Patent interpolation")."""

    def __init__(self, t, p, columns, rows, points):
        self.offsets = t[f"{p}_cell_offsets"].astype(np.int64)
        self.mirrors = t[f"{p}_cell_mirrors"].astype(np.int64)
        self.counts = t[f"{p}_cell_counts"].astype(np.float64)
        self.c, self.r, self.n = columns, rows, points

    def weights(self, d):
        theta = np.degrees(np.arccos(np.clip(d[2], -1, 1)))
        phi = np.degrees(np.arctan2(d[1], d[0])) % 360.0
        row = min(max(int(np.floor(theta / 90.0 * self.r)), 0), self.r - 1)
        col = min(max(int(np.floor(phi / 360.0 * self.c)), 0), self.c - 1)
        cell = row * self.c + col
        k = range(self.offsets[cell], self.offsets[cell + 1])
        return [(self.mirrors[i], self.counts[i] / self.n) for i in k]


def taps(n, x):
    """Step 4: bilinear taps of a wrapped coordinate on n texel centres."""
    x = x * n - 0.5
    x0 = np.floor(x)
    t = x - x0
    return min(max(int(x0), 0), n - 1), min(max(int(x0) + 1, 0), n - 1), t


def bilinear(img, u, v):
    """img[row t, column s, ...] at uv (already wrapped)."""
    s0, s1, ts = taps(img.shape[1], u)
    t0, t1, tt = taps(img.shape[0], v)
    return (1 - tt) * ((1 - ts) * img[t0, s0] + ts * img[t0, s1]) + tt * (
        (1 - ts) * img[t1, s0] + ts * img[t1, s1]
    )


def model(p, wi, wo):
    """The texel model M(wi, wo) per channel ("Texel model")."""
    rho, f0, alpha, nx, ny = p[0:3], p[3:6], p[6], p[7], p[8]
    n = np.array([nx, ny, np.sqrt(max(0.0, 1 - nx * nx - ny * ny))])
    ci, co = n @ wi, n @ wo
    if wi[2] <= 0 or wo[2] <= 0 or ci <= 0 or co <= 0:
        return np.zeros(3)
    h = unit(wi + wo)
    a2 = alpha * alpha
    d = a2 / (np.pi * ((n @ h) ** 2 * (a2 - 1) + 1) ** 2)

    def lam(c):
        return (np.sqrt(1 + a2 * (1 - c * c) / (c * c)) - 1) / 2

    g = 1 / (1 + lam(ci) + lam(co))
    f = f0 + (1 - f0) * (1 - wi @ h) ** 5
    return ci * (rho / np.pi + d * g * f / (4 * ci * co))


def check_digest(material):
    """The content digest ("The content digest"), which every file this
    builder writes carries."""
    b = open(material, "rb").read()
    n = struct.unpack("<Q", b[:8])[0]
    header = json.loads(b[8 : 8 + n])
    meta = header.pop("__metadata__")
    h = hashlib.sha256(meta["material"].encode() + b"\0")
    for name in sorted(header, key=lambda k: k.encode()):
        t = header[name]
        shape = ",".join(str(x) for x in t["shape"])
        begin, end = t["data_offsets"]
        h.update(f"{name}:{t['dtype']}:{shape}:{begin}-{end}\n".encode())
    h.update(b"\0" + b[8 + n :])
    if h.hexdigest() != meta["content_sha256"]:
        sys.exit(f"{material}: content digest {h.hexdigest()}, file says {meta['content_sha256']}")


def main(material, queries, answers):
    check_digest(material)
    t = load_file(material)
    with safe_open(material, "np") as f:
        meta = json.loads(f.metadata()["material"])
    lights = np.array([m["direction"] for m in meta["lights"]], dtype=np.float64)
    views = np.array([m["direction"] for m in meta["views"]], dtype=np.float64)
    pal = t["palettes"].astype(np.float64)
    idx = t["indices"].astype(np.int64)
    grp = t["light_groups"].astype(np.int64)
    interp = meta["interpolation"]
    patent = interp["kind"] == "patent"
    if patent:
        args = (interp["columns"], interp["rows"], interp["points"])
        light_w, view_w = Cells(t, "light", *args), Cells(t, "view", *args)
    else:
        light_w = Triangles(lights, t["light_triangles"])
        view_w = Triangles(views, t["view_triangles"])
    beta = meta["half_vector_shift"]
    texels = t["texel_model"].astype(np.float64) if meta.get("texel_model") else None
    detail = t["detail"].astype(np.float64) if meta.get("detail") else None
    r = meta.get("detail_components", 0) or 0
    enl = meta.get("enlargement")
    if enl:
        emap = t["enlargement"].astype(np.float64)
        ecols, erows = enl["columns"], enl["rows"]
        texel_mm = (meta["extent_mm"][0] / ecols, meta["extent_mm"][1] / erows)
        escale = [x / meta["sample_size_mm"] for x in texel_mm]
    if r:
        bases = t["detail_bases"].astype(np.float64)
        coef = t["detail_coefficients"].astype(np.float64)

    def image_at(l, v, u, w):
        """Pair (l, v)'s image at uv: its palette at bilinear taps."""
        img = idx[v, :, :, grp[l]]
        s0, s1, ts = taps(img.shape[1], u)
        t0, t1, tt = taps(img.shape[0], w)
        c = pal[l, v]
        return (1 - tt) * ((1 - ts) * c[img[t0, s0]] + ts * c[img[t0, s1]]) + tt * (
            (1 - ts) * c[img[t1, s0]] + ts * c[img[t1, s1]]
        )

    q = np.load(queries).astype(np.float64)
    out = np.zeros((len(q), 3), dtype=np.float32)
    for k, row in enumerate(q):
        u, w = row[0] - np.floor(row[0]), row[1] - np.floor(row[1])
        if enl:
            # Step 0: the piece's uv to the scanned sample's.
            x, y = u * ecols, w * erows
            c, rr = min(int(x), ecols - 1), min(int(y), erows - 1)
            top = 1 - 2.0**-23
            u = min(max((emap[rr, c, 0] + 0.5) / 65536 + (x - c - 0.5) * escale[0], 0.0), top)
            w = min(max((emap[rr, c, 1] + 0.5) / 65536 + (y - rr - 0.5) * escale[1], 0.0), top)
        wi, wo = unit(row[2:5]), unit(row[5:8])
        if wi[2] <= 0 or wo[2] <= 0:
            continue
        lw = light_w.weights(wi)
        # Steps 3–6: the pairs, each turned back into f by its light's cos θi.
        p = bilinear(texels, u, w) if texels is not None else None
        acc = np.zeros(3)
        if not patent and beta > 0:
            h = unit(wi + wo)
        for l, b in lw:
            if b == 0:
                continue
            if patent or beta == 0:
                vw = view_w.weights(wo)
            else:
                ref = 2 * (h @ lights[l]) * h - lights[l]
                vp = (1 - beta) * wo + beta * ref
                vp[2] = max(vp[2], 1e-4)
                vw = view_w.weights(unit(vp))
            for v, a in vw:
                if a == 0:
                    continue
                y = image_at(l, v, u, w)
                if p is not None:
                    y = y - model(p, lights[l], views[v])
                acc += a * b * y / lights[l][2]
        ans = wi[2] * acc
        if p is not None:
            ans = np.maximum(0.0, model(p, wi, wo) + ans)
        # Step 7: the detail layer.
        if detail is not None:
            log = np.zeros(3)
            if r:
                bs = np.array([b for _, b in lw])
                c = sum(b * coef[l] for l, b in lw) / bs.sum()
                log = sum(c[i] * bilinear(bases[i], u, w) for i in range(r))
            ans = ans * np.clip(bilinear(detail, u, w) * np.exp(log), 0.25, 4.0)
        out[k] = ans
    np.save(answers, out)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
