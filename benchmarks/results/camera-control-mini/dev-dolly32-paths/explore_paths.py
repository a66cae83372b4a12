"""Render-only (no model): mirror-pair PSNR per family on development scenes 0-7 for the path variants tried for
issue 32 (dolly32, 2026-12-04). Runs against the module of commit c093db5 (SCENES_VERSION 1, whose path functions
it calls): git show c093db5:benchmarks/camera_control_mini.py > DIR/benchmarks/camera_control_mini.py, then
python explore_paths.py DIR. A record of how the variants were chosen, not part of the benchmark."""
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[1] if len(sys.argv) > 1 else ".")  # a checkout of commit c093db5 (SCENES_VERSION 1)
from benchmarks import camera_control_mini as m
from navcrafter.models.simulation.render import render

T, R = 9, 32
kinds = ("room", "street", "tabletop")
seeds = range(0, 8)

def mirror_psnr(scene, poses_fn, a):
    p = m.render_path(scene, poses_fn(a)); q = m.render_path(scene, poses_fn(-a))
    return m.video_psnr(p, q), m.video_psnr(np.repeat(p[:1], T, 0), p)

def clear(scene, poses_fn, a, frames=4 * T):
    for _ in range(8):
        c = np.concatenate([poses_fn(s * a)[:, :3, 3] for s in (1, -1)])
        if np.all(scene.sim.distance(c) >= m.CLEARANCE):
            return a
        a *= 0.75
    return a

def near_point(scene, frac=0.2):
    r = render(scene.sim, scene.c2w0, m.Intrinsics.from_fov(float(scene.sim.camera_fov_x_deg), 64, 64), colour=False)
    K = m.Intrinsics.from_fov(float(scene.sim.camera_fov_x_deg), 64, 64).K
    v, u = np.nonzero(r.hit); z = r.depth[v, u]
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z; y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    pc = np.stack([x, y, z], 1)
    sel = z <= np.quantile(z, frac)
    c = pc[sel].mean(0)
    return scene.c2w0[:3, :3] @ c + scene.c2w0[:3, 3], float(np.median(z)), float(np.quantile(z, frac))

from navcrafter.models.camera.cameras import Intrinsics
m.Intrinsics = Intrinsics

def translate(c2w0, d):
    def f(a):
        out = np.repeat(c2w0[None], T, 0).copy()
        out[:, :3, 3] = c2w0[:3, 3] + np.outer(np.arange(T) / (T - 1), d * a)
        return out
    return f

def orbit(c2w0, centre):
    return lambda a: np.stack([m._about(centre, m._rz(np.deg2rad(a * k / (T - 1))), c2w0) for k in range(T)])

def freedist(scene, o, d):
    from navcrafter.models.simulation.datasets import _free_distance
    h = _free_distance(scene.sim, o, d)
    return h if np.isfinite(h) else 12.0

rows = {}
def add(name, fam, j, s, a, ps, c0):
    rows.setdefault(name, []).append((j, s, a, ps, c0))

t0 = time.time()
for j, s in enumerate(seeds):
    kind = kinds[j % 3]
    sc = m.make_scene(kind, s, R)
    rng = np.random.default_rng([0, s])
    amps = m.scene_amplitudes(sc, rng, T)
    ax = sc.c2w0[:3, 2]
    npt, zmed, znear = near_point(sc)
    back = freedist(sc, sc.c2w0[:3, 3], -ax)
    print(f"{kind}-{s}: L {sc.L:.2f} back {back:.2f} near-depth q20 {znear:.2f} median {zmed:.2f}", flush=True)
    for fam in m.FAMILIES:
        f = lambda a, fam=fam: m.path_poses(fam, a, T, sc.c2w0, sc.L)
        ps, c0 = mirror_psnr(sc, f, amps[fam])
        add(f"today {fam}", fam, j, s, amps[fam], ps, c0)
    # draw the dolly amplitude like today (same rng position is not reproducible; reuse today's drawn fraction)
    rng2 = np.random.default_rng([0, s]); draws = {f: rng2.uniform(*m.AMPLITUDES[f]) for f in m.FAMILIES}
    # D1: dolly toward the near-content centroid, metres = fraction of its distance
    d = npt - sc.c2w0[:3, 3]; dn = np.linalg.norm(d); d /= dn
    for nm, unit in (("dolly->near, x Lnear", dn), ("dolly->near, x L", sc.L)):
        a = clear(sc, translate(sc.c2w0, d), draws["dolly"] * unit)
        ps, c0 = mirror_psnr(sc, translate(sc.c2w0, d), a)
        add(nm, "dolly", j, s, a, ps, c0)
    def most_room(yaws, pitches):
        best = None
        for yaw in np.deg2rad(yaws):
            for pitch in np.deg2rad(pitches):
                dd = sc.c2w0[:3, :3] @ np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
                room = min(freedist(sc, sc.c2w0[:3, 3], dd), freedist(sc, sc.c2w0[:3, 3], -dd))
                if best is None or room > best[0] + 1e-9:
                    best = (room, dd)
        return best
    hf = np.rad2deg(np.arctan(np.tan(np.deg2rad(sc.sim.camera_fov_x_deg) / 2)))
    print("fov", sc.sim.camera_fov_x_deg, flush=True)
    bfr = most_room(np.linspace(-0.8 * hf, 0.8 * hf, 9), np.linspace(-0.8 * hf, 0.8 * hf, 9))
    print("chosen axis in camera frame", np.round(sc.c2w0[:3, :3].T @ bfr[1], 2), "room", round(bfr[0], 2),
          "fwd/back along view axis", round(sc.L, 2), round(back, 2), flush=True)
    b30 = most_room([-30, -20, -10, 0, 10, 20, 30], [-20, -10, 0, 10, 20])
    b45 = most_room(np.arange(-45, 46, 7.5), np.arange(-30, 31, 7.5))
    for nm, b, lo_hi in (("dolly most-room 30, 0.25-0.4 L", b30, (0.25, 0.4)),
                         ("dolly most-room 30, 0.4-0.6 L", b30, (0.4, 0.6)),
                         ("dolly most-room 45, 0.25-0.4 L", b45, (0.25, 0.4)),
                         ("dolly most-room 45, 0.4-0.6 L", b45, (0.4, 0.6)),
                         ("dolly axis, 0.4-0.6 L", (0, ax), (0.4, 0.6)),
                         ("dolly most-room 0.8 half-fov, 0.25-0.4 L", bfr, (0.25, 0.4)),
                         ("dolly most-room 0.8 half-fov, 0.4-0.6 L", bfr, (0.4, 0.6))):
        u = (draws["dolly"] - 0.25) / 0.15
        a = clear(sc, translate(sc.c2w0, b[1]), (lo_hi[0] + u * (lo_hi[1] - lo_hi[0])) * sc.L)
        ps, c0 = mirror_psnr(sc, translate(sc.c2w0, b[1]), a)
        add(nm, "dolly", j, s, a / sc.L, ps, c0)
        if "half-fov, 0.4" in nm: print(nm, "a/L", round(a / sc.L, 3), "metres", round(a, 2), flush=True)
    for fr in (0.25, 0.4, 0.55):
        f = orbit(sc.c2w0, sc.c2w0[:3, 3] + ax * fr * sc.L)
        a = clear(sc, f, draws["orbit"])
        ps, c0 = mirror_psnr(sc, f, a)
        add(f"orbit {fr} L", "orbit", j, s, a, ps, c0)
    f = orbit(sc.c2w0, sc.c2w0[:3, 3] + ax * 0.7 * sc.L)
    u = (draws["orbit"] - 20) / 20
    a = clear(sc, f, 30 + 20 * u)
    ps, c0 = mirror_psnr(sc, f, a)
    add("orbit 0.7 L, 30-50 deg", "orbit", j, s, a, ps, c0)
    f = orbit(sc.c2w0, sc.c2w0[:3, 3] + ax * 0.4 * sc.L)
    u = (draws["orbit"] - 20) / 20
    a = clear(sc, f, 30 + 20 * u)
    ps, c0 = mirror_psnr(sc, f, a)
    add("orbit 0.4 L, 30-50 deg", "orbit", j, s, a, ps, c0)
print(f"{time.time() - t0:.0f} s")
print("| variant | mirror-pair PSNR dB, mean (room / street / tabletop) | copy-frame-0 PSNR | amplitude min-max | per scene |")
for nm, r in rows.items():
    ps = np.array([x[3] for x in r]); kk = np.array([x[0] % 3 for x in r])
    print(f"| {nm} | {ps.mean():.2f} ({ps[kk==0].mean():.1f} / {ps[kk==1].mean():.1f} / {ps[kk==2].mean():.1f}) | "
          f"{np.mean([x[4] for x in r]):.2f} | {min(x[2] for x in r):.2f}-{max(x[2] for x in r):.2f} | "
          + " ".join(f"{x[3]:.1f}" for x in r) + " |")
