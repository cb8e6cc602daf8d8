#!/usr/bin/env python3
"""The pose of a view from a neighbouring view's photo (docs/measurements.md, twenty-seventh
session): the SIFT flow from A to its neighbour B (the .flo files `photo_to_photo_flow.py`
writes), B's pixels lifted to 3D with B's pose and a depth for them, then RANSAC PnP (OpenCV's
EPnP, 2 px, then Levenberg–Marquardt on the inliers). The depth is B's exact depth (`exact`, an
upper bound) or the LoD model's (`lod`: the model registration is given, ray cast here); B's
pose is the true one or turned by TURN_DEG about its centre in a random direction (a registered
neighbour's error: 0.15° is about 0.9 px at this focal length). δ: the mean distance between
A's own visible points (exact depth) projected with the estimated and the true pose, px.
Needs numpy and opencv-python-headless.

Usage: python3 docs/scripts/pose_from_neighbour.py SCENE FLO_DIR [TURN_DEG] [exact|lod]"""
import sys, glob, os
import numpy as np
import cv2

def read_ply(path):
    with open(path, 'rb') as fh:
        header = []
        while True:
            line = fh.readline().decode().strip(); header.append(line)
            if line == 'end_header': break
        nv = int([l for l in header if l.startswith('element vertex')][0].split()[-1])
        nf = int([l for l in header if l.startswith('element face')][0].split()[-1])
        V = np.frombuffer(fh.read(nv * 24), '<f8').reshape(nv, 3)
        faces = []
        for _ in range(nf):
            n = fh.read(1)[0]
            faces.append(np.frombuffer(fh.read(4 * n), '<i4'))
        F = np.array([fc[:3] for fc in faces])
        return V, F
def depth_at(V, F, R, t, us, vs, f, cx, cy):
    """Depth (camera z) of the first triangle hit by each pixel ray (us, vs: pixel coords with
    centres at +0.5), 0 where none."""
    P = V @ R.T + t
    A, B, C = P[F[:,0]], P[F[:,1]], P[F[:,2]]
    e1, e2 = B - A, C - A
    d = np.stack([(us - cx) / f, (vs - cy) / f, np.ones_like(us)], -1)
    out = np.zeros(len(us))
    for s in range(0, len(us), 2000):
        D = d[s:s+2000][:, None, :]
        pvec = np.cross(D, e2[None])
        det = np.einsum('rtk,tk->rt', pvec, e1)
        inv = 1.0 / np.where(np.abs(det) < 1e-12, np.nan, det)
        tvec = -A[None]
        u = np.einsum('rtk,tk->rt', pvec, tvec[0]) * inv
        qvec = np.cross(tvec[0][None], e1[None])[0]
        v = np.einsum('rk,tk->rt', D[:,0,:], qvec) * inv
        z = np.einsum('tk,tk->t', e2, qvec)[None] * inv
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (z > 1e-6)
        z = np.where(hit, z, np.inf)
        best = z.min(1)
        out[s:s+2000] = np.where(np.isfinite(best), best, 0)
    return out

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from photo_to_photo_flow import read_pfm, read_flo, load_scene

scene, flodir = sys.argv[1], sys.argv[2]
W, H, f, cx, cy, poses = load_scene(scene)
turn_deg = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
use_lod = len(sys.argv) > 4 and sys.argv[4] == "lod"

rng = np.random.default_rng(1)
LOD = read_ply(f"{scene}/model_lod.ply")
res = []
for flo in sorted(glob.glob(f"{flodir}/*.flo")):
    a, b = os.path.basename(flo)[:-4].split('-')
    F = read_flo(flo)
    Ra, ta = poses[a]; Rb, tb = poses[b]
    if turn_deg > 0:
        axis = rng.normal(size=3); axis /= np.linalg.norm(axis)
        dR, _ = cv2.Rodrigues(axis * np.radians(turn_deg))
        Rb_used = dR @ Rb; tb_used = dR @ tb  # turned about B's camera centre
    else:
        Rb_used, tb_used = Rb, tb
    db = read_pfm(f"{scene}/depth_exact/{b.replace('.jpg','.pfm')}")
    da = read_pfm(f"{scene}/depth_exact/{a.replace('.jpg','.pfm')}")
    ys, xs = np.mgrid[2:H-2:3, 2:W-2:3]
    ys = ys.ravel(); xs = xs.ravel()
    pu = xs + 0.5; pv = ys + 0.5
    qu = pu + F[ys, xs, 0]; qv = pv + F[ys, xs, 1]
    ok = np.isfinite(qu) & np.isfinite(qv) & (qu >= 0) & (qu < W) & (qv >= 0) & (qv < H) & (np.abs(F[ys, xs, 0]) < 1e5)
    qi = np.clip(qu.astype(int), 0, W-1); qj = np.clip(qv.astype(int), 0, H-1)
    if use_lod:
        V, Fc = LOD
        d = np.zeros(len(qu))
        d[ok] = depth_at(V, Fc, Rb_used, tb_used, qu[ok], qv[ok], f, cx, cy)
    else:
        d = db[qj, qi]
    ok &= d > 0
    Xc = np.stack([(qu-cx)/f*d, (qv-cy)/f*d, d], -1)
    Xw = (Xc - tb_used) @ Rb_used
    obj = Xw[ok].astype(np.float64); img = np.stack([pu, pv], -1)[ok].astype(np.float64)
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    # COLMAP pixel centres at +0.5: OpenCV's at 0 -> shift by 0.5 for OpenCV.
    okp, rvec, tvec, inl = cv2.solvePnPRansac(obj, img - 0.5, K, None, reprojectionError=2.0, iterationsCount=2000, flags=cv2.SOLVEPNP_EPNP)
    if not okp or inl is None or len(inl) < 6:
        res.append((a, b, None, 0)); print(a, b, "no pose"); continue
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl[:,0]], img[inl[:,0]] - 0.5, K, None, rvec, tvec)
    Re, _ = cv2.Rodrigues(rvec); te = tvec.ravel()
    # δ over A's own visible points (exact depth of A).
    ya, xa = np.mgrid[0:H:4, 0:W:4]; ya = ya.ravel(); xa = xa.ravel()
    dA = da[ya, xa]; m = dA > 0
    XcA = np.stack([(xa+0.5-cx)/f*dA, (ya+0.5-cy)/f*dA, dA], -1)[m]
    XwA = (XcA - ta) @ Ra
    Pe = XwA @ Re.T + te
    ue = f*Pe[:,0]/Pe[:,2] + cx; ve = f*Pe[:,1]/Pe[:,2] + cy
    delta = np.mean(np.hypot(ue - (xa[m]+0.5), ve - (ya[m]+0.5)))
    res.append((a, b, delta, len(inl)))
    print(f"{a} <- {b}: δ {delta:6.2f} px ({len(inl)} inliers of {len(obj)})", flush=True)
ds = np.array([r[2] if r[2] is not None else 1e9 for r in res])
print(f"{len(res)} frames: δ ≤ 1 / 2 / 5 px: {(ds<=1).sum()} / {(ds<=2).sum()} / {(ds<=5).sum()}; median {np.median(ds):.2f} px")
