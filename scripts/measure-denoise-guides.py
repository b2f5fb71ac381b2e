#!/usr/bin/env python3
# How far could an edge-aware spatial filter of ONE 4-spp frame get, given a better guide? The
# filter's twin in numpy (isowall_render::denoise::filter_with, checked here against the GPU's own
# `--denoise on` render), run on isowalld's 4-spp occlusion with the occlusion stop guided by:
#   - the 4-spp estimate itself (the renderer's filter);
#   - a raw 32-spp render (a guide 8x better sampled than the signal);
#   - the reference (64 spp x 16 frames, another seed): an oracle no renderer has,
# with the renderer's plane and normal stops, and for the oracle also looser ones. The RMSE of
# each against the reference over the hit pixels, beside raw 4 and raw 32 spp's.
#
# Usage: scripts/measure-denoise-guides.py [ISOWALLD]   (ISOWALLD: target/debug/isowalld)
# Needs numpy (pip install numpy). Run from the checkout's root with ../shared beside it.
import os, subprocess, sys, tempfile
import numpy as np

BIN = os.path.abspath(sys.argv[1] if len(sys.argv) > 1 else "target/debug/isowalld")
SCENES = [
    # name, render arguments, eye, target (fov 40, up +z, 512x512)
    ("engine", ["--volume", "procedural:engine"], [128, -300, 300], [128, 128, 59]),
    ("mri", ["--volume", "../shared/data/mri-brainsmall.nrrd", "--iso", "40"], [63.5, -170, 120], [63.5, 63.5, 41.5]),
]
SIZE = 512
B3 = [3 / 8, 1 / 4, 1 / 16]


def pfm(path):
    with open(path, "rb") as f:
        kind = f.readline().strip()
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    c = 3 if kind == b"PF" else 1
    a = data.reshape(h, w, c)[::-1]  # PFM rows run bottom to top
    return a if c == 3 else a[..., 0]


def rays(eye, target, fov, w, h):
    """DESIGN.md's pixel-centre rays."""
    eye = np.array(eye, float)
    f = np.array(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    t = np.tan(np.radians(fov) / 2)
    px, py = np.meshgrid(np.arange(w), np.arange(h))
    sx = ((px + 0.5) / w * 2 - 1) * t * w / h
    sy = (1 - (py + 0.5) / h * 2) * t
    d = f[None, None, :] + sx[..., None] * r + sy[..., None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True), t


def shifted(a, dx, dy, fill):
    h, w = a.shape[:2]
    out = np.full_like(a, fill)
    ys, xs = slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))
    yd, xd = slice(max(0, dy), min(h, h + dy)), slice(max(0, dx), min(w, w + dx))
    out[ys, xs] = a[yd, xd]
    return out


def filt(a, var, hit, pos, nrm, depth, tan_half, guide=None, guide_sigma=None, sp=1.0, so=2.0, ns=5):
    """The renderer's 5 a-trous passes; with `guide`, the occlusion stop compares the guide's
    values with a fixed sigma instead of the signal's with its variance."""
    h = a.shape[0]
    sig, v = a.copy(), var.copy()
    footprint = sp * depth * 2 * tan_half / h
    for p in range(5):
        st = 1 << p
        s_sum, w_sum, v_sum = np.zeros_like(a), np.zeros_like(a), np.zeros_like(a)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                sh = lambda x, fill=0: shifted(x, dx * st, dy * st, fill)
                offset = np.sqrt((dx * dx + dy * dy) * st * st)
                plane = np.abs(np.sum(nrm * (sh(pos) - pos), -1))
                w_plane = np.exp(-plane / np.maximum(footprint * offset, 1e-20))
                w_normal = np.maximum(np.sum(nrm * sh(nrm), -1), 0) ** (2**ns)
                sq, vq = sh(sig), sh(v)
                if guide is None:
                    sigma = so * np.sqrt(np.maximum(np.maximum(v, vq), 0)) + 1e-6
                    w_occ = np.exp(-np.abs(sig - sq) / sigma)
                else:
                    w_occ = np.exp(-np.abs(guide - sh(guide)) / guide_sigma)
                wq = np.where(sh(hit, False) & hit, B3[abs(dx)] * B3[abs(dy)] * w_plane * w_normal * w_occ, 0)
                s_sum += wq * sq
                w_sum += wq
                v_sum += wq * wq * vq
        ok = w_sum > 0
        sig = np.where(ok, s_sum / np.where(ok, w_sum, 1), sig)
        v = np.where(ok, v_sum / np.where(ok, w_sum * w_sum, 1), v)
    return sig


def main():
    work = tempfile.mkdtemp(prefix="isowall-guides-")
    for name, args, eye, target in SCENES:
        cam = ["--size", f"{SIZE}x{SIZE}", "--eye", ",".join(map(str, eye)), "--target",
               ",".join(map(str, target)), "--up", "0,0,1", "--fov-y", "40"]
        out = lambda k: os.path.join(work, f"{name}-{k}.pfm")
        renders = [(k, ["--ao-samples", "0", "--aov", k]) for k in ("depth", "normal", "hit")] + [
            ("occ4", ["--ao-samples", "4", "--aov", "occlusion"]),
            ("occ32", ["--ao-samples", "32", "--aov", "occlusion"]),
            ("den4", ["--ao-samples", "4", "--denoise", "on", "--aov", "occlusion"]),
            ("ref", ["--ao-samples", "64", "--frames", "16", "--seed", "7", "--aov", "occlusion"]),
        ]
        for k, extra in renders:
            subprocess.run([BIN, "render", *args, *cam, *extra, "--out", out(k)], check=True, capture_output=True)
        depth, nrm, hit = pfm(out("depth")), pfm(out("normal")), pfm(out("hit")) > 0.5
        o4, o32, den4, ref = (pfm(out(k)) for k in ("occ4", "occ32", "den4", "ref"))
        dirs, tan_half = rays(eye, target, 40, SIZE, SIZE)
        pos = dirs * depth[..., None]
        p = (4 * o4 + 1) / 6
        var = p * (1 - p) / 4

        def rmse(x):
            e = (x - ref)[hit]
            return float(np.sqrt(np.mean(e * e)))

        base = lambda **kw: filt(o4, var, hit, pos, nrm, depth, tan_half, **kw)
        twin = base()
        print(f"{name}: {int(hit.sum())} hit pixels, reference mean A {ref[hit].mean():.4f}; "
              f"numpy twin vs the GPU's --denoise on: max |diff| {np.abs(twin - den4)[hit].max():.1e}")
        print(f"  raw 4 spp {rmse(o4):.4f}, raw 32 spp {rmse(o32):.4f}, filtered 4 spp (GPU) {rmse(den4):.4f}")
        for label, guide in (("raw 32 spp", o32), ("oracle (the reference)", ref)):
            for gs in (0.01, 0.02, 0.05, 0.1):
                print(f"  guide {label}, sigma {gs}: {rmse(base(guide=guide, guide_sigma=gs)):.4f}")
        for sp, ns, what in ((4.0, 2, "looser plane and normal stops"), (1e6, 0, "no plane or normal stop")):
            for gs in (0.02, 0.05, 0.1):
                r = rmse(base(guide=ref, guide_sigma=gs, sp=sp, ns=ns))
                print(f"  guide oracle, sigma {gs}, {what}: {r:.4f}")


main()
