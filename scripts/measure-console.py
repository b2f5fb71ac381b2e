#!/usr/bin/env python3
# One run: fps without and with the console page open, the page's thumbnail latency, bytes per
# second, a killed node's card turning down and back up. Drives Debian's chromium through
# chromedriver's WebDriver REST API (urllib only).
#
# Usage: scripts/measure-console.py WALL.toml [BIN_DIR] [ROUNDS]   (BIN_DIR: target/debug; ROUNDS: 3)
# fps: ROUNDS pairs of 10 s windows, the page closed (the browser on about:blank) then open, in
# turn, so that load from elsewhere on a shared machine falls on both alike; the ratio printed is
# the median of the pairs' ratios. ISOWALL_BROWSER_NICE=N runs chromium at that niceness (an
# operator's browser runs on another machine: this keeps its own drawing off the wall's cores).
# The wall must be on loopback (the console starts its nodes with --local); its keys are made in
# a temporary folder beside a copy of the config.
import json, subprocess, time, urllib.request, base64, os, signal, sys, shutil, tempfile
if len(sys.argv) < 2:
    sys.exit(__doc__ or "usage: scripts/measure-console.py WALL.toml [BIN_DIR]")
BIN = os.path.abspath(sys.argv[2] if len(sys.argv) > 2 else "target/debug")
work = tempfile.mkdtemp(prefix="isowall-console-")
shutil.copy(sys.argv[1], os.path.join(work, "w.toml"))
os.chdir(work)
def http(method, url, body=None):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.loads(r.read())
subprocess.run([BIN + "/isowall", "keygen", "--config", "w.toml"], check=True, capture_output=True)
con = subprocess.Popen([BIN + "/isowall", "console", "w.toml", "--local", "--listen", "127.0.0.1:18090"],
                       stdout=open("out.txt", "w"), stderr=open("err.txt", "w"))
base = "http://127.0.0.1:18090"
t0 = time.time()
while True:
    try:
        s = http("GET", base + "/api/status")
        if all(n["state"] == "up" for n in s["nodes"]): break
    except Exception: pass
    if time.time() - t0 > 300: sys.exit("no wall")
    time.sleep(0.5)
time.sleep(5)
TICK = os.sysconf("SC_CLK_TCK")
def tree(root):
    """root and every process below it (from /proc)."""
    kids = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(open(f"/proc/{d}/stat").read().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
            kids.setdefault(ppid, []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop(); out.append(p); todo += kids.get(p, [])
    return out
def cpu(pids):
    """CPU seconds (user + system) the processes have used so far, their children that ended included."""
    t = 0
    for p in pids:
        try:
            f = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
            t += sum(int(x) for x in f[11:15])
        except OSError:
            pass
    return t / TICK
def window(sec):
    """fps, image B/s, served B/s, thumbnails/s, the status, and the CPU cores the wall (console and
    its nodes) and the browser (chromedriver and its chromium) used, over sec seconds."""
    wall, web = tree(con.pid), tree(drv.pid)
    c0 = (cpu(wall), cpu(web))
    a = http("GET", base + "/api/status"); time.sleep(sec); b = http("GET", base + "/api/status")
    c1 = (cpu(wall), cpu(web))
    dt = b["console"]["uptime_s"] - a["console"]["uptime_s"]
    d = lambda k: (b["console"][k] - a["console"][k]) / dt
    return ((b["frame"]["released"] - a["frame"]["released"]) / dt, d("node_image_bytes"), d("served_bytes"),
            d("thumbnails"), b, (c1[0] - c0[0]) / dt, (c1[1] - c0[1]) / dt)
ROUNDS = int(sys.argv[3]) if len(sys.argv) > 3 else 3
drv = subprocess.Popen(["chromedriver", "--port=19515"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
time.sleep(2)
browser = "/usr/bin/chromium"
nice = os.environ.get("ISOWALL_BROWSER_NICE")
if nice:
    browser = os.path.join(work, "chromium-niced")
    with open(browser, "w") as f:
        f.write(f"#!/bin/sh\nexec nice -n {int(nice)} /usr/bin/chromium \"$@\"\n")
    os.chmod(browser, 0o755)
args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--window-size=1280,1200",
        # The page closed must be closed: no back-forward cache keeping it (and its WebSocket).
        "--disable-features=BackForwardCache", "--user-data-dir=" + os.path.join(work, "profile")]
sess = http("POST", "http://127.0.0.1:19515/session",
            {"capabilities": {"alwaysMatch": {"goog:chromeOptions": {"binary": browser, "args": args}}}})
sid = sess["value"]["sessionId"]
W = "http://127.0.0.1:19515/session/" + sid
http("POST", W + "/url", {"url": base + "/"})
js = lambda e: http("POST", W + "/execute/sync", {"script": "return (" + e + ");", "args": []})["value"]
t = time.time()
while not js("window.isowall && window.isowall.thumbnails >= 1"):
    time.sleep(0.1)
first = time.time() - t
time.sleep(5)
lat = []
pairs = []
cores = []
for _ in range(ROUNDS):
    http("POST", W + "/url", {"url": "about:blank"})
    time.sleep(2)
    fps0, img0, srv0, th0, s0, wc0, bc0 = window(10)
    http("POST", W + "/url", {"url": base + "/"})
    while not js("window.isowall && window.isowall.thumbnails >= 1"):
        time.sleep(0.1)
    time.sleep(2)
    fps1, img1, srv1, th1, s1, wc1, bc1 = window(10)
    lat += js("window.isowall.latencies")
    pairs.append((fps0, fps1))
    cores.append((wc0, bc0, wc1, bc1))
    print(f"  pair: fps without page {fps0:.2f}, with page {fps1:.2f}, ratio {fps1/fps0:.3f}; CPU cores used: "
          f"wall {wc0:.2f} -> {wc1:.2f}, browser {bc0:.3f} -> {bc1:.3f}", flush=True)
lat.sort()
ratios = sorted(b / a for a, b in pairs)
pid = [n for n in s1["nodes"] if n["name"] == "node1"][0]["pid"]
os.kill(pid, signal.SIGKILL); k = time.time()
while js("document.querySelector('.node-card[data-node=\"node1\"]').dataset.state") != "down":
    time.sleep(0.05)
down = time.time() - k
shot_down = http("GET", W + "/screenshot")["value"]
d = subprocess.Popen([BIN + "/isowalld", "run", "--config", "w.toml", "--node", "node1"],
                     stdout=open("node1-restart.log", "w"), stderr=subprocess.STDOUT)
r = time.time()
while js("document.querySelector('.node-card[data-node=\"node1\"]').dataset.state") != "up":
    time.sleep(0.1)
up = time.time() - r
time.sleep(4)
open("console.png", "wb").write(base64.b64decode(http("GET", W + "/screenshot")["value"]))
open("console-node-down.png", "wb").write(base64.b64decode(shot_down))
http("DELETE", W)
drv.kill(); con.send_signal(signal.SIGINT); time.sleep(3); d.kill()
med = lat[len(lat)//2] if lat else float("nan")
print(f"first thumbnail {first*1e3:.0f} ms after navigation")
print(f"thumbnail latency over {len(lat)} thumbnails: median {med:.0f} ms, min {lat[0]:.0f}, max {lat[-1]:.0f}")
print(f"fps over {len(pairs)} pairs of 10 s windows: without page median {sorted(a for a, _ in pairs)[len(pairs)//2]:.2f}, "
      f"with page median {sorted(b for _, b in pairs)[len(pairs)//2]:.2f}; ratio per pair median {ratios[len(ratios)//2]:.3f} "
      f"(min {ratios[0]:.3f}, max {ratios[-1]:.3f}); browser niceness {nice or 0}")
med_of = lambda i: sorted(c[i] for c in cores)[len(cores)//2]
print(f"CPU cores used (median of the windows): wall {med_of(0):.2f} without the page, {med_of(2):.2f} with it; "
      f"browser {med_of(1):.3f} on about:blank, {med_of(3):.3f} with the page")
print(f"node->controller image B/s: {img0:.0f} without, {img1:.0f} with; console->page {srv1:.0f} B/s; thumbnails/s asked {th1:.2f}")
print(f"node1 killed -> card down {down*1e3:.0f} ms (deadline 3000 ms); restarted -> up {up*1e3:.0f} ms")
print("wall", s1["wall"]["width"], "x", s1["wall"]["height"], "frame p50", s1["frame"]["frame_ms_p50"], "skew p50/p99", s1["frame"]["skew_ms_p50"], s1["frame"]["skew_ms_p99"])
