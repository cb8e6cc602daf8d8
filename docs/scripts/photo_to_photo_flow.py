#!/usr/bin/env python3
"""Photo-to-photo SIFT flow between neighbouring views of a synthetic scene (`asgreg synth`),
against the true flow made from the exact depth (`depth_exact/`) and the true poses (`gt/`):
how accurate correspondences taken from a neighbour's photo would be, next to the photo-to-ASG
flow that registration uses (`eval --diagnose`'s flow error). Each view is paired with the
nearest other view (camera centres) looking within 30° of it; pixels are kept where A sees a
surface, it lands inside B at least 20 px from the border, and B's exact depth there agrees
within 2 % (not occluded). `asgreg flow --preset fast` makes the flow.
(docs/measurements.md, twenty-seventh session.)

Usage: python3 docs/scripts/photo_to_photo_flow.py SCENE ASGREG_BINARY OUT_DIR [PAIRS]"""
import sys, os, subprocess
import numpy as np

def read_pfm(p):
    with open(p, 'rb') as f:
        f.readline(); w, h = map(int, f.readline().split()); s = float(f.readline())
        d = np.frombuffer(f.read(), dtype='<f4' if s < 0 else '>f4').reshape(h, w)
        return np.flipud(d).astype(np.float64)
def read_flo(p):
    with open(p, 'rb') as f:
        assert np.frombuffer(f.read(4), '<f4')[0] == 202021.25
        w, h = np.frombuffer(f.read(8), '<i4')
        return np.frombuffer(f.read(), '<f4').reshape(h, w, 2).astype(np.float64)
def quat_to_R(qw, qx, qy, qz):
    return np.array([[1-2*(qy*qy+qz*qz), 2*(qx*qy-qz*qw), 2*(qx*qz+qy*qw)],
                     [2*(qx*qy+qz*qw), 1-2*(qx*qx+qz*qz), 2*(qy*qz-qx*qw)],
                     [2*(qx*qz-qy*qw), 2*(qy*qz+qx*qw), 1-2*(qx*qx+qy*qy)]])
def load_scene(scene):
    """The scene's PINHOLE camera (W, H, f, cx, cy) and true poses {name: (R, t)}, cam_from_world."""
    with open(f"{scene}/gt/cameras.txt") as fh:
        cam = fh.read().strip().splitlines()[-1].split()
    W, H, f, cx, cy = int(cam[2]), int(cam[3]), float(cam[4]), float(cam[6]), float(cam[7])
    poses = {}
    with open(f"{scene}/gt/images.txt") as fh:
        lines = [l for l in fh if not l.startswith('#')]
    for l in lines[::2]:
        t = l.split()
        if len(t) < 10: continue
        R = quat_to_R(*map(float, t[1:5])); tr = np.array(list(map(float, t[5:8])))
        poses[t[9]] = (R, tr)
    return W, H, f, cx, cy, poses

def main():
    scene, asgreg, out = sys.argv[1], sys.argv[2], sys.argv[3]
    npairs = int(sys.argv[4]) if len(sys.argv) > 4 else 12
    os.makedirs(out, exist_ok=True)
    W, H, f, cx, cy, poses = load_scene(scene)
    names = sorted(poses)
    centres = {n: -poses[n][0].T @ poses[n][1] for n in names}
    axes = {n: poses[n][0][2] for n in names}
    # Each view's nearest other view by centre distance among those looking within 30 degrees.
    pairs = []
    for a in names:
        cands = [(np.linalg.norm(centres[a]-centres[b]), b) for b in names if b != a and axes[a] @ axes[b] > np.cos(np.radians(30))]
        if cands:
            pairs.append((a, min(cands)[1], min(cands)[0]))
    pairs = pairs[:npairs]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rows = []
    for a, b, dist in pairs:
        da = read_pfm(f"{scene}/depth_exact/{a.replace('.jpg','.pfm')}")
        db = read_pfm(f"{scene}/depth_exact/{b.replace('.jpg','.pfm')}")
        Ra, ta = poses[a]; Rb, tb = poses[b]
        Xc = np.stack([(u-cx)/f*da, (v-cy)/f*da, da], -1)
        Xw = (Xc - ta) @ Ra  # R^T (x - t)
        Xb = Xw @ Rb.T + tb
        ub = f*Xb[...,0]/Xb[...,2] + cx; vb = f*Xb[...,1]/Xb[...,2] + cy
        valid = (da > 0) & (Xb[...,2] > 0) & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
        # Occlusion: B's exact depth at the landing pixel agrees within 2 %.
        ib = np.clip(ub.astype(int), 0, W-1); jb = np.clip(vb.astype(int), 0, H-1)
        valid &= np.abs(db[jb, ib] - Xb[...,2]) < 0.02 * Xb[...,2]
        margin = np.zeros_like(valid); margin[20:-20, 20:-20] = True
        valid &= margin
        flo = f"{out}/{a}-{b}.flo"
        subprocess.run([asgreg, "flow", "--preset", "fast", "--out", flo, f"{scene}/images/{a}", f"{scene}/images/{b}"], check=True, capture_output=True)
        F = read_flo(flo)
        epe = np.hypot(F[...,0] - (ub - u), F[...,1] - (vb - v))[valid]
        true_mag = np.hypot(ub-u, vb-v)[valid]
        rows.append((a, b, dist, valid.mean(), np.median(true_mag), np.median(epe), (epe <= 1).mean(), (epe <= 2).mean(), (epe <= 5).mean()))
        print(f"{a} -> {b}: {dist:5.2f} m apart, {100*valid.mean():4.1f} % pixels, true flow median {np.median(true_mag):6.1f} px, EPE median {np.median(epe):5.2f} px, <=1/2/5 px {100*(epe<=1).mean():4.0f} / {100*(epe<=2).mean():4.0f} / {100*(epe<=5).mean():4.0f} %", flush=True)
    r = np.array([x[2:] for x in rows])
    print(f"mean over {len(rows)} pairs: true flow median {r[:,2].mean():.1f} px, EPE median {r[:,3].mean():.2f} px, <=1/2/5 px {100*r[:,4].mean():.0f} / {100*r[:,5].mean():.0f} / {100*r[:,6].mean():.0f} %")

if __name__ == "__main__":
    main()
