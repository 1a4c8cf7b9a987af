"""Refit with exact ranges on the truth cameras and on the poses step's COLMAP frames (a diagnostic).

Usage: python benchmarks/bench_refit_geometry.py RUN PIXELS_PER_VIEW SEEDS VARIANTS
e.g. results/demo 12800 0,1,2,3 truth,colmap_sim_tp,colmap_sim,colmap_train; VF=2 scales the
0.054 m voxel. Variants: truth (simulator images, own cameras), truth_box/truth_box2 (2x2 blend of
colour / colour and range), colmap_sim (simulator images undistorted onto COLMAP frames),
colmap_sim_tp (the same grouped by the true points), colmap_train (the training images); a
"+q" suffix keeps the smoothest q share of surface pixels; "~W" averages each pixel's colour
over an image box W metres across at its range, "~W@S" also leaves out pixels whose box spans a
relative range spread above S ("~W@-S": only that, colours unaveraged). Environment: DIRBIN=a
groups by voxel and by viewing direction (cells of a in each component of the unit vector),
NODARK=1 fits without the dark-pixel bound, BWFLOOR=f floors the brightness weights at f times
the median (water_fit.brightness_weights). c_med is in each geometry's units.
Prints how far COLMAP's cameras are from the truth, then errors against the true water, %, R G B."""
import os
import sys
import numpy as np, torch
from pathlib import Path; sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from seathru.io.cameras import read_cameras
from seathru.io.images import read_image
from seathru.io.water import read_truth_water
from seathru.io.evaluation import camera_centres, truth_on_frames
from seathru.io.stored_views import source_cameras, stored_image_on_frame
from seathru.eval import truth as truth_eval
from seathru.nerf import water_fit, water_surfaces
from seathru.nerf.rays import frame_rays

RUN = sys.argv[1]; PER_VIEW = int(sys.argv[2]); SEEDS = [int(s) for s in sys.argv[3].split(",")]
VARIANTS = sys.argv[4].split(",")
torch.set_num_threads(1)
truth_dir = f"{RUN}/simulate/truth"
tcams = read_cameras(f"{truth_dir}/cameras.json")
ccams = read_cameras(f"{RUN}/poses/cameras.json")
tw = read_truth_water(f"{truth_dir}/water.json").as_dict()
mpu = truth_eval.camera_metric_scale(camera_centres(ccams), camera_centres(tcams, source_units=True), ccams.scale).scale
on_frame = truth_on_frames(ccams)
candidates = source_cameras(ccams)
tframes = {f.name: f for f in tcams.frames}
VOXEL_M = 0.054 * float(os.environ.get("VF", "1"))


def camera_error() -> str:
    """COLMAP's cameras against the simulator's: orientation after the best
    common rotation, centres after a similarity alignment (metres), focal length."""
    from seathru.geometry.poses import compare_trajectories, rotation_angle_deg
    names = [f.name for f in ccams.frames]
    est = np.array([f.c2w_array for f in ccams.frames])
    ref = np.array([tframes[n].c2w_array for n in names])
    u, _, vt = np.linalg.svd(sum(r[:3, :3] @ e[:3, :3].T for e, r in zip(est, ref)))
    common = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    turn = rotation_angle_deg(common @ est[:, :3, :3], ref[:, :3, :3])
    centres = compare_trajectories(est, ref).position_errors / tcams.scale
    focal = ccams.frames[0].fx   # COLMAP's undistortion crops the frame, keeps the focal
    return (f"cameras: orientation {np.median(turn):.3f} deg median ({turn.max():.3f} largest), "
            f"centres {1000 * np.median(centres):.1f} mm median ({1000 * centres.max():.1f}), "
            f"focal {100 * (focal / tframes[names[0]].fx - 1):+.2f}%")


print(camera_error(), flush=True)

def box(img):   # 2x2 box blend (what a half-pixel bilinear shift does)
    out = img.copy()
    out[:-1, :-1] = 0.25 * (img[:-1, :-1] + img[1:, :-1] + img[:-1, 1:] + img[1:, 1:])
    return out

def local_contrast(img):
    import cv2
    lum = img.sum(-1).astype(np.float32)
    lum = np.where(np.isfinite(lum), lum, 0)
    hi = cv2.dilate(lum, np.ones((3, 3), np.uint8)); lo = cv2.erode(lum, np.ones((3, 3), np.uint8))
    return ((hi - lo) / np.maximum(hi + lo, 1e-6)).reshape(-1)

def footprint_mean(img, rng_m, fx, width_m, spread=None):
    """Each pixel's colour averaged over an image box width_m metres across at its range
    (summed-area table, continuous box corners; NaN pixels left out)."""
    h, w = img.shape[:2]
    valid = np.isfinite(img).all(-1)
    val = np.where(valid[..., None], img, 0.0).astype(np.float64)
    sat = np.zeros((h + 1, w + 1, 4))
    sat[1:, 1:, :3] = val.cumsum(0).cumsum(1)
    sat[1:, 1:, 3] = valid.cumsum(0).cumsum(1)
    half = np.where(np.isfinite(rng_m) & (rng_m > 0), 0.5 * width_m * fx / np.where(rng_m > 0, rng_m, 1), 0.5)
    half = np.maximum(half, 0.5).reshape(h, w)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    def at(y, x):   # bilinear read of the table at continuous (y, x)
        y = np.clip(y, 0, h); x = np.clip(x, 0, w)
        y0 = np.minimum(np.floor(y).astype(int), h - 1); x0 = np.minimum(np.floor(x).astype(int), w - 1)
        ty = (y - y0)[..., None]; tx = (x - x0)[..., None]
        return ((1 - ty) * ((1 - tx) * sat[y0, x0] + tx * sat[y0, x0 + 1])
                + ty * ((1 - tx) * sat[y0 + 1, x0] + tx * sat[y0 + 1, x0 + 1]))
    def box_sum():
        return (at(yy + half, xx + half) - at(yy - half, xx + half) - at(yy + half, xx - half)
                + at(yy - half, xx - half))
    s = box_sum()
    out = s[..., :3] / np.maximum(s[..., 3:], 1e-9)
    out = np.where(valid[..., None], out, np.nan)
    if spread is not None:   # leave out pixels whose box spans more than `spread` in range
        r = np.where(np.isfinite(rng_m) & (rng_m > 0), rng_m, 0.0).reshape(h, w)
        fin = (np.isfinite(rng_m) & (rng_m > 0)).reshape(h, w)
        sat[:] = 0
        sat[1:, 1:, 0] = r.cumsum(0).cumsum(1); sat[1:, 1:, 1] = (r * r).cumsum(0).cumsum(1)
        sat[1:, 1:, 2] = fin.cumsum(0).cumsum(1)
        sat[1:, 1:, 3] = np.ones((h, w)).cumsum(0).cumsum(1)
        t = box_sum()
        m = t[..., 0] / np.maximum(t[..., 2], 1e-9); var = t[..., 1] / np.maximum(t[..., 2], 1e-9) - m * m
        bad = fin & ((t[..., 2] < t[..., 3] - 1e-6) | (np.sqrt(np.maximum(var, 0)) > spread * np.maximum(m, 1e-9)))
        out[bad] = np.nan
    return out.reshape(-1, 3)

def view_data(name, variant):
    """origins, dirs (normalised), rgb, range (normalised), units per metre"""
    if variant.startswith("truth"):
        f = tframes[name]
        o, d = frame_rays(f)
        rgb = read_image(f"{truth_dir}/water/{name}.tiff")[..., :3]
        depth = read_image(f"{truth_dir}/depth/{name}.tiff")
        depth = depth[..., 0] if depth.ndim == 3 else depth
        if variant in ("truth_box", "truth_box2"):
            rgb = box(rgb)
        if variant == "truth_box2":
            depth = box(np.where(np.isfinite(depth) & (depth > 0), depth, np.nan))
        per_m = tcams.scale
    else:
        f = next(fr for fr in ccams.frames if fr.name == name)
        o, d = frame_rays(f)
        depth = on_frame(read_image(f"{truth_dir}/depth/{name}.tiff"), name)
        if variant in ("colmap_sim_tp", "colmap_train_tp"):
            tf = tframes[name]
            to, td = frame_rays(tf)
            tdepth = read_image(f"{truth_dir}/depth/{name}.tiff")
            tdepth = tdepth[..., 0] if tdepth.ndim == 3 else tdepth
            pts = (to + td * torch.from_numpy(np.where(np.isfinite(tdepth), tdepth, np.nan).reshape(-1, 1).astype(np.float32)) * tcams.scale).numpy()
            pts = pts / tcams.scale    # metres (shifted)
            # points are not colours: bilinear whatever the poses step used for the images
            wp = stored_image_on_frame(pts.reshape(tf.height, tf.width, 3), f, candidates,
                                       "linear").reshape(-1, 3) / mpu
            rr = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).reshape(-1) / mpu
            o = torch.from_numpy(np.nan_to_num(wp - d.numpy() * np.where(np.isfinite(rr), rr, 0)[:, None]).astype(np.float32))
        if variant in ("colmap_sim", "colmap_sim_tp"):
            rgb = on_frame(read_image(f"{truth_dir}/water/{name}.tiff")[..., :3], name)
        else:   # colmap_train: the pipeline's training images
            rgb = read_image(ccams.image_path(f))[..., :3]
        per_m = 1.0 / mpu
        raw = read_image(f"{truth_dir}/depth/{name}.tiff")
        raw = raw[..., 0] if raw.ndim == 3 else raw
        share = on_frame((~(np.isfinite(raw) & (raw > 0))).astype(np.float32), name)
        depth = np.where(share > 0.999, np.inf, np.where(share < 0.001, depth, np.nan))
        return o, d, rgb.reshape(-1, 3), depth.reshape(-1) * per_m, per_m
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
    return o, d, rgb.reshape(-1, 3), depth.reshape(-1) * per_m, per_m

train_names = [f.name for f in ccams.split("train")]
SHAPE = {f.name: (f.height, f.width) for f in ccams.frames}
TSHAPE = {f.name: (f.height, f.width) for f in tcams.frames}
for spec in VARIANTS:
    variant, _, q = spec.partition("+")
    variant, _, foot = variant.partition("~")
    foot, _, spread = foot.partition("@")
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        parts = [[], [], [], []]
        for name in train_names:
            o, d, rgb, rng_, per_m = view_data(name, variant)
            if foot:
                fr = tframes[name] if variant.startswith("truth") else next(x for x in ccams.frames if x.name == name)
                plain = rgb
                rgb = footprint_mean(rgb.reshape(fr.height, fr.width, 3), rng_ / per_m, fr.fx, float(foot), abs(float(spread)) if spread else None)
                if spread.startswith("-"):   # only the selection: colours as they were
                    rgb = np.where(np.isfinite(rgb).all(1, keepdims=True), plain, np.nan)
            good = np.isfinite(rgb).all(1) & ~np.isnan(rng_)
            if q:
                c = local_contrast(rgb.reshape(*(TSHAPE if variant.startswith("truth") else SHAPE)[name], 3))
                surf = good & np.isfinite(rng_)
                cut = np.quantile(c[surf], float(q))
                good &= ~surf | (c <= cut)
            ok = np.flatnonzero(good)
            pick = rng.choice(ok, min(PER_VIEW, len(ok)), replace=False)
            parts[0].append(o[pick].double()); parts[1].append(d[pick].double())
            parts[2].append(torch.from_numpy(rgb[pick].astype(np.float64)))
            parts[3].append(torch.from_numpy(rng_[pick]))
        o, d, rgb, rr = (torch.cat(p) for p in parts)
        ow = ~torch.isfinite(rr)
        pids = None
        if os.environ.get("DIRBIN"):   # group by voxel and by a cell of the viewing direction
            fin = torch.isfinite(rr)
            pts = o + d * torch.where(fin, rr, 0)[:, None]
            key = torch.cat([torch.floor(pts / (VOXEL_M * per_m)), torch.floor(d / float(os.environ["DIRBIN"]))], 1).long()
            _, pids = torch.unique(key, dim=0, return_inverse=True)
            pids = torch.where(fin, pids, -1)
        data = water_surfaces.surface_data(o, d, rgb, torch.where(ow, torch.nan, rr), (~ow).double(),
                                      VOXEL_M * per_m, 0.9, open_water_opacity=0.5, open_water=ow,
                                      point_ids=pids)
        fit = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups,
                                  {"sigma_attn": 0.2 / per_m, "sigma_bs": 0.2 / per_m, "c_med": 0.2},
                                  dark=None if os.environ.get("NODARK") else data.dark,
                                  brightness_floor=float(os.environ.get("BWFLOOR", "1")))
        err = {k: [100 * (float(v) * per_m / t - 1) for v, t in zip(getattr(fit, k), tw[k])]
               for k in ("sigma_attn", "sigma_bs", "c_med")}
        print(f"{spec:18s} seed {seed}: sa " + " ".join(f"{e:+5.1f}" for e in err["sigma_attn"])
              + " | sbs " + " ".join(f"{e:+5.1f}" for e in err["sigma_bs"]) + " | cmed " + " ".join(f"{e:+5.1f}" for e in err["c_med"]), flush=True)
