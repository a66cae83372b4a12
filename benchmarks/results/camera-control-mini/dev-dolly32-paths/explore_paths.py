"""Render-only (no model): mirror-pair PSNR per family on development scenes 0-7 for the path variants tried for
issue 32 (dolly32, 2026-12-04). Runs against the module of commit c093db5 (SCENES_VERSION 1, whose path functions
it calls): ``git show c093db5:benchmarks/camera_control_mini.py > DIR/benchmarks/camera_control_mini.py`` (with an
empty ``DIR/benchmarks/__init__.py``), then ``python explore_paths.py DIR > explore_paths.txt``. A record of how
SCENES_VERSION 2's dollies and orbits were chosen, not part of the benchmark; free distances here count open sky
as 12 m (the benchmark's ``dolly_axis`` counts it as unbounded: one street axis differs, 16.53 here vs 16.62 dB)."""

import sys
import time

import numpy as np

T, R = 9, 32
KINDS = ("room", "street", "tabletop")


def mirror_psnr(m, scene, poses_fn, a):
    p, q = m.render_path(scene, poses_fn(a)), m.render_path(scene, poses_fn(-a))
    return m.video_psnr(p, q), m.video_psnr(np.repeat(p[:1], T, 0), p)


def clear(m, scene, poses_fn, a):
    """Shrink ``a`` by 0.75 (at most 8 times) until the path and its mirror keep CLEARANCE (scene_amplitudes')."""
    for _ in range(8):
        c = np.concatenate([poses_fn(s * a)[:, :3, 3] for s in (1, -1)])
        if np.all(scene.sim.distance(c) >= m.CLEARANCE):
            return a
        a *= 0.75
    return a


def near_point(scene, frac=0.2):
    """The centroid of the nearest ``frac`` of the first camera's pixels (64² depth render) and depth quantiles."""
    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.simulation.render import render

    intr = Intrinsics.from_fov(float(scene.sim.camera_fov_x_deg), 64, 64)
    r = render(scene.sim, scene.c2w0, intr, colour=False)
    K = intr.K
    v, u = np.nonzero(r.hit)
    z = r.depth[v, u]
    pc = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
    c = pc[z <= np.quantile(z, frac)].mean(0)
    return scene.c2w0[:3, :3] @ c + scene.c2w0[:3, 3], float(np.median(z)), float(np.quantile(z, frac))


def translate(c2w0, d):
    def f(a):
        out = np.repeat(c2w0[None], T, 0).copy()
        out[:, :3, 3] = c2w0[:3, 3] + np.outer(np.arange(T) / (T - 1), d * a)
        return out
    return f


def orbit(m, c2w0, centre):
    return lambda a: np.stack([m._about(centre, m._rz(np.deg2rad(a * k / (T - 1))), c2w0) for k in range(T)])


def freedist(scene, o, d):
    from navcrafter.models.simulation.datasets import _free_distance

    h = _free_distance(scene.sim, o, d)
    return h if np.isfinite(h) else 12.0


def most_room(sc, yaws, pitches):
    best = None
    for yaw in np.deg2rad(yaws):
        for pitch in np.deg2rad(pitches):
            local = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
            dd = sc.c2w0[:3, :3] @ local
            room = min(freedist(sc, sc.c2w0[:3, 3], dd), freedist(sc, sc.c2w0[:3, 3], -dd))
            if best is None or room > best[0] + 1e-9:
                best = (room, dd)
    return best


def scene_rows(m, j, s, add):
    sc = m.make_scene(KINDS[j % 3], s, R)
    amps = m.scene_amplitudes(sc, np.random.default_rng([0, s]), T)
    ax = sc.c2w0[:3, 2]
    npt, zmed, znear = near_point(sc)
    back = freedist(sc, sc.c2w0[:3, 3], -ax)
    print(f"{KINDS[j % 3]}-{s}: L {sc.L:.2f} back {back:.2f} near-depth q20 {znear:.2f} median {zmed:.2f}",
          flush=True)
    for fam in m.FAMILIES:
        ps, c0 = mirror_psnr(m, sc, lambda a, fam=fam: m.path_poses(fam, a, T, sc.c2w0, sc.L), amps[fam])
        add(f"today {fam}", j, amps[fam], ps, c0)
    # each variant reuses today's drawn fraction of its family's range
    rng = np.random.default_rng([0, s])
    draws = {f: rng.uniform(*m.AMPLITUDES[f]) for f in m.FAMILIES}
    d = npt - sc.c2w0[:3, 3]
    dn = np.linalg.norm(d)
    d /= dn
    for nm, unit in (("dolly->near, x Lnear", dn), ("dolly->near, x L", sc.L)):
        a = clear(m, sc, translate(sc.c2w0, d), draws["dolly"] * unit)
        add(nm, j, a, *mirror_psnr(m, sc, translate(sc.c2w0, d), a))
    hf = sc.sim.camera_fov_x_deg / 2
    print("fov", sc.sim.camera_fov_x_deg, flush=True)
    bfr = most_room(sc, np.linspace(-0.8 * hf, 0.8 * hf, 9), np.linspace(-0.8 * hf, 0.8 * hf, 9))
    print("chosen axis in camera frame", np.round(sc.c2w0[:3, :3].T @ bfr[1], 2), "room", round(bfr[0], 2),
          "fwd/back along view axis", round(sc.L, 2), round(back, 2), flush=True)
    b30 = most_room(sc, [-30, -20, -10, 0, 10, 20, 30], [-20, -10, 0, 10, 20])
    b45 = most_room(sc, np.arange(-45, 46, 7.5), np.arange(-30, 31, 7.5))
    u = (draws["dolly"] - 0.25) / 0.15
    for nm, b, (lo, hi) in (("dolly most-room 30, 0.25-0.4 L", b30, (0.25, 0.4)),
                            ("dolly most-room 30, 0.4-0.6 L", b30, (0.4, 0.6)),
                            ("dolly most-room 45, 0.25-0.4 L", b45, (0.25, 0.4)),
                            ("dolly most-room 45, 0.4-0.6 L", b45, (0.4, 0.6)),
                            ("dolly axis, 0.4-0.6 L", (0, ax), (0.4, 0.6)),
                            ("dolly most-room 0.8 half-fov, 0.25-0.4 L", bfr, (0.25, 0.4)),
                            ("dolly most-room 0.8 half-fov, 0.4-0.6 L", bfr, (0.4, 0.6))):
        a = clear(m, sc, translate(sc.c2w0, b[1]), (lo + u * (hi - lo)) * sc.L)
        add(nm, j, a / sc.L, *mirror_psnr(m, sc, translate(sc.c2w0, b[1]), a))
        if "half-fov, 0.4" in nm:
            print(nm, "a/L", round(a / sc.L, 3), "metres", round(a, 2), flush=True)
    for fr in (0.25, 0.4, 0.55):
        f = orbit(m, sc.c2w0, sc.c2w0[:3, 3] + ax * fr * sc.L)
        a = clear(m, sc, f, draws["orbit"])
        add(f"orbit {fr} L", j, a, *mirror_psnr(m, sc, f, a))
    for fr in (0.7, 0.4):
        f = orbit(m, sc.c2w0, sc.c2w0[:3, 3] + ax * fr * sc.L)
        a = clear(m, sc, f, 30 + 20 * (draws["orbit"] - 20) / 20)
        add(f"orbit {fr} L, 30-50 deg", j, a, *mirror_psnr(m, sc, f, a))


def main():
    sys.path.insert(0, sys.argv[1] if len(sys.argv) > 1 else ".")  # a checkout of commit c093db5's module
    from benchmarks import camera_control_mini as m

    rows = {}
    t0 = time.time()
    for j, s in enumerate(range(8)):
        scene_rows(m, j, s, lambda name, j, a, ps, c0: rows.setdefault(name, []).append((j, a, ps, c0)))
    print(f"{time.time() - t0:.0f} s")
    print("| variant | mirror-pair PSNR dB, mean (room / street / tabletop) | copy-frame-0 PSNR | amplitude min-max "
          "| per scene |")
    for nm, r in rows.items():
        ps, kk = np.array([x[2] for x in r]), np.array([x[0] % 3 for x in r])
        print(f"| {nm} | {ps.mean():.2f} ({ps[kk == 0].mean():.1f} / {ps[kk == 1].mean():.1f} / "
              f"{ps[kk == 2].mean():.1f}) | {np.mean([x[3] for x in r]):.2f} | {min(x[1] for x in r):.2f}-"
              f"{max(x[1] for x in r):.2f} | " + " ".join(f"{x[2]:.1f}" for x in r) + " |")


if __name__ == "__main__":
    main()
