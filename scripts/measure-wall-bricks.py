#!/usr/bin/env python3
"""A local 2x2 wall reading a store through each node's brick cache, against the same wall
holding it whole: the converged still's pixels and the orbit's frame rate.

Converts VOLUME (default ../shared/data/ct-cranium.nrrd) to an OME-Zarr store with bricks of
CHUNK (32), writes a wall config of four local nodes (2x2 tiles of TILE_W x TILE_H, `[volume]
iso = ISO`), then for the whole store and for each GPU budget (MiB a node; the host budget the
same):
- still: `isowall up CONFIG --frames 1 --still-frames 30 --snapshot` without AO (so that a
  restarted accumulation is the same picture): the values that differ from the whole store's
  snapshot, and the report's `level 0 (brick cache)` line;
- orbit: `isowall up CONFIG --frames 60 --degrees-per-frame 3` with AO samples AO: its fps line.

Usage: scripts/measure-wall-bricks.py [BIN_DIR] [BUDGET_MIB ...]
  BIN_DIR: target/debug (needs isowall and isowalld: `cargo build -p isowall -p isowalld`)
  BUDGET_MIB: default 32 8 2
Environment: VOLUME, ISO (480), CHUNK (32), TILE_W (160), TILE_H (120), AO (4), KEEP=1 keeps the
work folder.
"""
import os, re, shutil, struct, subprocess, sys, tempfile, zlib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from local_wall import free_ports  # noqa: E402

args = sys.argv[1:]
BIN = os.path.abspath(args.pop(0) if args and not re.match(r"^\d", args[0]) else "target/debug")
budgets = [int(a) for a in args] or [32, 8, 2]
VOLUME = os.path.abspath(os.environ.get("VOLUME", "../shared/data/ct-cranium.nrrd"))
ISO = os.environ.get("ISO", "480")
CHUNK = os.environ.get("CHUNK", "32")
TW, TH = int(os.environ.get("TILE_W", "160")), int(os.environ.get("TILE_H", "120"))
AO = int(os.environ.get("AO", "4"))
for exe in ["isowall", "isowalld"]:
    if not os.path.exists(os.path.join(BIN, exe)):
        sys.exit(f"{BIN}/{exe} is missing: cargo build -p isowall -p isowalld")


def config(work, name, volume_lines, render_lines):
    bezel = 4
    s = (f'[wall]\nname = "{name}"\ndeadline_ms = 60000\n\n[volume]\nsource = "store.ome.zarr"\n'
         f'iso = {ISO}\n{volume_lines}\n[render]\n{render_lines}env = "sky"\n\n[certificates]\ndir = "keys"\n')
    for i, port in enumerate(free_ports(4)):
        cx, cy = i % 2, i // 2
        b = [0 if cx == 0 else bezel, bezel if cx == 0 else 0, 0 if cy == 0 else bezel, bezel if cy == 0 else 0]
        s += (f'\n[[tiles]]\nname = "t{cx}{cy}"\nx = {cx * (TW + 2 * bezel)}\ny = {cy * (TH + 2 * bezel)}\n'
              f'width = {TW}\nheight = {TH}\nbezel = {b}\n'
              f'\n[[nodes]]\nname = "node{i}"\naddress = "127.0.0.1:{port}"\ntiles = ["t{cx}{cy}"]\n')
    path = os.path.join(work, name + ".toml")
    with open(path, "w") as f:
        f.write(s)
    return path


def png_rows(path):
    """An 8-bit RGB(A) PNG's rows (no interlace), without an imaging library."""
    data, i, idat = open(path, "rb").read(), 8, b""
    while i < len(data):
        n, kind = struct.unpack(">I4s", data[i:i + 8])
        chunk = data[i + 8:i + 8 + n]
        i += 12 + n
        if kind == b"IHDR":
            w, h, _, color = struct.unpack(">IIBB", chunk[:10])
        elif kind == b"IDAT":
            idat += chunk
    bpp = {2: 3, 6: 4}[color]
    raw, stride, rows, prev, k = zlib.decompress(idat), w * bpp, [], bytearray(w * bpp), 0
    for _ in range(h):
        f, line = raw[k], bytearray(raw[k + 1:k + 1 + stride])
        k += 1 + stride
        for x in range(stride):
            a = line[x - bpp] if x >= bpp else 0
            b, c = prev[x], (prev[x - bpp] if x >= bpp else 0)
            if f == 1:
                line[x] = (line[x] + a) & 255
            elif f == 2:
                line[x] = (line[x] + b) & 255
            elif f == 3:
                line[x] = (line[x] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return rows


def up(work, cfg, extra):
    out = subprocess.run([os.path.join(BIN, "isowall"), "up", cfg, "--start-timeout", "120"] + extra,
                         cwd=work, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"isowall up {cfg} failed:\n{out.stderr[-3000:]}")
    return out.stdout


work = tempfile.mkdtemp(prefix="wall-bricks-")
try:
    out = subprocess.run([os.path.join(BIN, "isowalld"), "convert", VOLUME, "store.ome.zarr", "--chunk", CHUNK],
                         cwd=work, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(out.stderr)
    print(out.stdout.strip().splitlines()[-1])
    still_render = 'ao_samples = 0\nibl = "none"\n'
    orbit_render = f'ao_samples = {AO}\nibl = "{"bent" if AO else "none"}"\n'
    runs = [("whole", "")] + [(f"gpu{b}", f"gpu_budget_mb = {b}\nhost_budget_mb = {b}\n") for b in budgets]
    keys = None
    reference = None
    for name, lines in runs:
        still = config(work, f"{name}-still", lines, still_render)
        orbit = config(work, f"{name}-orbit", lines, orbit_render)
        if keys is None:
            subprocess.run([os.path.join(BIN, "isowall"), "keygen", "--config", still], cwd=work,
                           check=True, capture_output=True)
            keys = True
        report = up(work, still, ["--frames", "1", "--still-frames", "30", "--snapshot", f"{name}.png"])
        rows = png_rows(os.path.join(work, f"{name}.png"))
        if reference is None:
            reference = rows
            differ = "reference"
        else:
            n = sum(x != y for a, b in zip(rows, reference) for x, y in zip(a, b))
            total = sum(len(r) for r in rows)
            differ = f"{n} of {total} values differ from the whole store's"
        level0 = next((l for l in report.splitlines() if l.startswith("level 0")), "(no brick cache)")
        print(f"{name} still: {differ}; {level0}")
        fps = next(l for l in up(work, orbit, ["--frames", "60", "--degrees-per-frame", "3"]).splitlines()
                   if l.startswith("frames:"))
        print(f"{name} orbit: {fps}")
finally:
    if os.environ.get("KEEP") == "1":
        print(f"kept {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
