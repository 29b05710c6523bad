#!/usr/bin/env python3
"""Independent checks of the STL tiles that `biscale design` exports into OUTDIR.

Per exported detail: mesh checks with trimesh (and, when installed, ADMesh, PrusaSlicer --info and
a headless PrusaSlicer slice to G-code), then a drop-cutter simulation of the profile's ball-nose
tool on the central period of the tile (OpenCAMLib, or an exact numpy drop-cutter when OpenCAMLib
is missing or --numpy is given). The max and RMS of (made - design) are compared with summary.json:
pass if |ours - theirs| <= 0.01 mm + 5 % of theirs.
Usage: verify_export.py OUTDIR [--numpy] [--spacing-frac F]   (grid spacing <= F * tool radius)
"""
import json, math, re, shutil, subprocess, sys, tempfile, time, tomllib
from pathlib import Path
import numpy as np
import trimesh

try:
    import opencamlib as ocl
except ImportError:
    ocl = None
ROOT = Path(__file__).resolve().parent.parent


def read_stl(path):
    """Binary STL -> (stored normals (n,3), triangles (n,3,3)) in float64."""
    data = path.read_bytes()
    n = int(np.frombuffer(data, "<u4", 1, 80)[0])
    rec = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), n, 84)
    return rec["n"].astype(float), rec["v"].astype(float)


def load_profile(ref, base=ROOT / "profiles/fabrication"):
    """A fabrication profile as a dict, `extends` chains merged (name or path, as biscale takes)."""
    p = (base / ref) if ("/" in ref or ref.endswith(".toml")) else ROOT / "profiles/fabrication" / f"{ref}.toml"
    prof = tomllib.loads(p.read_text())
    return {**load_profile(prof["extends"], p.parent), **prof} if "extends" in prof else prof


def tool_diameter(summary):
    """(tool name, ball diameter mm) of the design's profile; diameter None for printers and
    flat-end tools. From the resolved profile that summary.json records (any profile, shipped or
    the user's own, with the catalogue it was resolved against), else (older outputs) by looking
    the profile name up among the shipped profiles."""
    fab = summary.get("fabrication_profile")
    if fab is not None:
        tool = fab.get("tool")
        if not tool:
            return None, None
        return tool["name"], (tool["diameter_mm"] if tool["kind"] == "ball" else None)
    prof = load_profile(summary["profile"])
    if "tool" not in prof:
        return None, None
    tool = tomllib.loads((ROOT / "constraints/tools.toml").read_text())[prof["tool"]]
    return prof["tool"], (tool["diameter_mm"] if tool["kind"] == "ball" else None)


def mesh_checks(path, meta, tris, normals):
    """trimesh + ADMesh + stored-normal checks; returns list of (name, ok, detail)."""
    m = trimesh.load_mesh(path, process=True)
    out = [("watertight", m.is_watertight, ""), ("winding consistent", m.is_winding_consistent, ""),
           ("is_volume", m.is_volume, ""), ("volume > 0", m.volume > 0, f"{m.volume:.3f} mm3"),
           ("euler = 2 (genus 0)", m.euler_number == 2, f"euler {m.euler_number}")]
    e = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area2 = np.linalg.norm(e, axis=1)
    good = area2 > 1e-12
    dots = np.einsum("ij,ij->i", e[good] / area2[good, None], normals[good])
    out.append(("stored normals = CCW normals", bool(dots.min() > 0.99), f"min dot {dots.min():.4f}, "
                f"{(~good).sum()} zero-area facets"))
    lo, hi = m.bounds
    px = meta["mm_per_pixel"]
    tx, ty = meta["tile_mm"]
    size_ok = abs(hi[0] - lo[0] - tx) <= px and abs(hi[1] - lo[1] - ty) <= px and np.allclose(lo, 0, atol=1e-6)
    out.append(("bbox x,y = tile (to 1 sample)", size_ok, f"{hi[0]-lo[0]:.4f} x {hi[1]-lo[1]:.4f} mm"))
    top = tris[(e[:, 2] > 1e-12)]
    zmin_top = top[:, :, 2].min()
    out.append(("top min = base", abs(zmin_top - meta["base"]) < 1e-4, f"{zmin_top:.4f} vs {meta['base']}"))
    out.append(("z max = json z_max_mm", abs(hi[2] - meta["zmax"]) < 1e-3, f"{hi[2]:.4f} vs {meta['zmax']:.4f}"))
    if shutil.which("admesh"):
        txt = subprocess.run(["admesh", "--exact", str(path)], capture_output=True, text=True).stdout
        vals = {k: int(re.search(rf"{k}\s*:\s*(\d+)", txt).group(1)) for k in
                ("Total disconnected facets", "Degenerate facets", "Backwards edges", "Facets reversed")}
        out.append(("admesh --exact", all(v == 0 for v in vals.values()),
                    ", ".join(f"{k.split()[0].lower()} {v}" for k, v in vals.items())))
    else:
        out.append(("admesh", True, "not installed, skipped"))
    return out + prusa_checks(path, m.volume)


def prusa_checks(path, volume):
    """PrusaSlicer --info (manifold, facets, volume vs trimesh to 0.5 %) and a headless slice to G-code."""
    exe = shutil.which("prusa-slicer")
    if not exe:
        return [("prusa-slicer", True, "not installed, skipped")]
    txt = subprocess.run([exe, "--info", str(path)], capture_output=True, text=True).stdout
    info = dict(re.findall(r"^(\w+)\s*=\s*(.*?)\s*$", txt, re.M))
    pv = float(info.get("volume", "nan"))
    out = [("prusa-slicer --info manifold", info.get("manifold") == "yes",
            f"manifold = {info.get('manifold', '?')}, {info.get('number_of_facets', '?')} facets"
            + (f", {info['open_edges']} open edges" if "open_edges" in info else "")),
           ("prusa volume = trimesh (0.5 %)", abs(pv - volume) <= 0.005 * abs(volume), f"{pv:.3f} vs {volume:.3f} mm3")]
    with tempfile.TemporaryDirectory() as tmp:
        gcode = Path(tmp) / f"{path.stem}.gcode"
        t0 = time.monotonic()
        r = subprocess.run([exe, "--loglevel", "1", "--export-gcode", "--output", str(gcode), str(path)],
                           capture_output=True, text=True)
        dt = time.monotonic() - t0
        ok = r.returncode == 0 and gcode.is_file() and gcode.stat().st_size > 0
        if ok:
            g = gcode.read_text()
            est = re.search(r"estimated printing time \(normal mode\) = (.*)", g)
            info = f"{g.count(';LAYER_CHANGE')} layers, est. print {est.group(1) if est else '?'}, sliced in {dt:.1f} s"
        else:
            info = f"exit {r.returncode}: {(r.stderr.strip() or r.stdout.strip() or 'no output').splitlines()[-1]}"
    return out + [("prusa-slicer --export-gcode", ok, info)]


def drop_numpy(tris, cx, cy, r):
    """Exact ball-nose drop: tool-tip z at each (cx, cy) = max over triangles of vertex, edge and
    facet contact heights. Loops over triangles, vectorised over the CL points under each."""
    X, Y = np.meshgrid(cx, cy)
    tip = np.full(X.shape, -np.inf)
    hx, hy = cx[1] - cx[0], cy[1] - cy[0]
    for t in tris:
        i0 = max(0, int(math.floor((t[:, 0].min() - r - cx[0]) / hx)))
        i1 = min(len(cx), int(math.ceil((t[:, 0].max() + r - cx[0]) / hx)) + 1)
        j0 = max(0, int(math.floor((t[:, 1].min() - r - cy[0]) / hy)))
        j1 = min(len(cy), int(math.ceil((t[:, 1].max() + r - cy[0]) / hy)) + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        x, y = X[j0:j1, i0:i1], Y[j0:j1, i0:i1]
        h = np.full(x.shape, -np.inf)
        for v in t:  # vertex contacts
            d2 = (x - v[0]) ** 2 + (y - v[1]) ** 2
            h = np.maximum(h, np.where(d2 <= r * r, v[2] + np.sqrt(np.maximum(r * r - d2, 0)) - r, -np.inf))
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):  # edge contacts
            L = math.hypot(b[0] - a[0], b[1] - a[1])
            if L < 1e-12:
                continue
            ux, uy, m = (b[0] - a[0]) / L, (b[1] - a[1]) / L, (b[2] - a[2]) / L
            u = (x - a[0]) * ux + (y - a[1]) * uy
            d2 = (x - a[0]) ** 2 + (y - a[1]) ** 2 - u * u
            s = np.sqrt(np.maximum(r * r - d2, 0))
            q = math.sqrt(1 + m * m)
            w = u + s * m / q
            ok = (d2 <= r * r) & (w >= 0) & (w <= L)
            h = np.maximum(h, np.where(ok, a[2] + m * u + s * q - r, -np.inf))
        n = np.cross(t[1] - t[0], t[2] - t[0])
        if n[2] > 1e-12 * np.linalg.norm(n):  # facet contact (upward facets only)
            n = n / np.linalg.norm(n)
            px, py = x - r * n[0], y - r * n[1]
            inside = point_in_tri(t, px, py)
            zp = t[0, 2] - (n[0] * (px - t[0, 0]) + n[1] * (py - t[0, 1])) / n[2]
            h = np.maximum(h, np.where(inside, zp + r * n[2] - r, -np.inf))
        tip[j0:j1, i0:i1] = np.maximum(tip[j0:j1, i0:i1], h)
    return tip


def point_in_tri(t, px, py, eps=1e-9):
    (ax, ay), (bx, by), (cx_, cy_) = t[0, :2], t[1, :2], t[2, :2]
    d = (by - cy_) * (ax - cx_) + (cx_ - bx) * (ay - cy_)
    l1 = ((by - cy_) * (px - cx_) + (cx_ - bx) * (py - cy_)) / d
    l2 = ((cy_ - ay) * (px - cx_) + (ax - cx_) * (py - cy_)) / d
    return (l1 >= -eps) & (l2 >= -eps) & (1 - l1 - l2 >= -eps)


def drop_ocl(tris, cx, cy, r):
    surf = ocl.STLSurf()
    for t in tris:
        surf.addTriangle(ocl.Triangle(*(ocl.Point(*map(float, v)) for v in t)))
    bdc = ocl.BatchDropCutter()
    bdc.setSTL(surf)
    cutter = ocl.BallCutter(2 * r, 10.0)  # keep a reference: OCL stores a raw pointer
    bdc.setCutter(cutter)
    zmin = float(tris[:, :, 2].min()) - 1.0
    for y in cy:
        for x in cx:
            bdc.appendPoint(ocl.CLPoint(float(x), float(y), zmin))
    bdc.run()
    return np.array([p.z for p in bdc.getCLPoints()]).reshape(len(cy), len(cx))


def design_height(tris, X, Y):
    """Top-surface height of the mesh at the points: the highest upward facet above each point."""
    z = np.full(X.shape, -np.inf)
    for t in tris:
        n = np.cross(t[1] - t[0], t[2] - t[0])
        if n[2] <= 1e-12 * np.linalg.norm(n):
            continue
        m = (X >= t[:, 0].min() - 1e-9) & (X <= t[:, 0].max() + 1e-9) & (Y >= t[:, 1].min() - 1e-9) & (Y <= t[:, 1].max() + 1e-9)
        if not m.any():
            continue
        px, py = X[m], Y[m]
        zp = np.where(point_in_tri(t, px, py), t[0, 2] - (n[0] * (px - t[0, 0]) + n[1] * (py - t[0, 1])) / n[2], -np.inf)
        z[m] = np.maximum(z[m], zp)
    return z


def simulate(tris, patch, tile, r, frac, use_numpy):
    """Drop the ball on the central period; returns (max, rms) of made - design, grid size, engine."""
    k = int(min(tile) / patch) // 2
    x0 = y0 = k * patch
    n = math.ceil(patch / (frac * r))
    h = patch / n
    pad = math.ceil(r / h)
    cx = x0 + h * np.arange(-pad, n + pad)
    cy = y0 + h * np.arange(-pad, n + pad)
    lo, hi = x0 - 2 * r - h, x0 + patch + 2 * r + h
    keep = (tris[:, :, 0].max(1) >= lo) & (tris[:, :, 0].min(1) <= hi) & (tris[:, :, 1].max(1) >= lo) & (tris[:, :, 1].min(1) <= hi)
    sub = tris[keep]
    engine = "numpy" if (use_numpy or ocl is None) else "opencamlib"
    cl = (drop_numpy if engine == "numpy" else drop_ocl)(sub, cx, cy, r)
    made = np.full((n, n), np.inf)  # lower envelope of the ball over the CL points within r
    for dj in range(-pad, pad + 1):
        for di in range(-pad, pad + 1):
            d2 = (di * h) ** 2 + (dj * h) ** 2
            if d2 <= r * r:
                made = np.minimum(made, cl[pad + dj:pad + dj + n, pad + di:pad + di + n] + r - math.sqrt(r * r - d2))
    X, Y = np.meshgrid(cx[pad:pad + n], cy[pad:pad + n])
    dev = made - design_height(sub, X, Y)
    return float(dev.max()), float(np.sqrt(np.mean(dev ** 2))), float(dev.min()), n, h, engine


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if len(args) != 1:
        sys.exit(__doc__)
    frac = float(next((a.split("=")[1] for a in sys.argv if a.startswith("--spacing-frac=")), 0.125))
    out = Path(args[0])
    if not (out / "summary.json").is_file():
        sys.exit(f"verify-export: {out}: no summary.json here; expected an output directory of "
                 f"`biscale design` (outputs/<scene name>)")
    summary = json.loads((out / "summary.json").read_text())
    if not any(d.get("stl") for d in summary["details"]):
        sys.exit(f"verify-export: {out}: the design exported no STL (details = 0, or no candidate "
                 f"was feasible: see its report.md); nothing to check")
    tool, diameter = tool_diameter(summary)
    failures, rows = 0, []
    print(f"{out}: profile {summary['profile']}, tool {tool} ({diameter} mm ball), "
          f"drop-cutter: {'numpy' if ('--numpy' in sys.argv or ocl is None) else 'opencamlib ' + ocl.version()}")
    for d in summary["details"]:
        if not d.get("stl"):
            continue
        scale = json.loads((out / d["heightmap_scale"]).read_text())
        meta = {"mm_per_pixel": scale["mm_per_pixel"], "tile_mm": d["tile_mm"], "base": scale["base_thickness_mm"],
                "zmax": scale["z_max_mm"]}
        normals, tris = read_stl(out / d["stl"])
        print(f"\n{d['stl']}: {len(tris)} triangles, patch {d['patch_mm']:.4f} mm, tool {d['tool']}")
        for name, ok, info in mesh_checks(out / d["stl"], meta, tris, normals):
            failures += not ok
            print(f"  {'ok  ' if ok else 'FAIL'} {name:30s} {info}")
        if diameter is None or d["tool"] != tool:
            print("  (no ball-nose tool: drop-cutter skipped)")
            continue
        mx, rms, mn, n, h, eng = simulate(tris, d["patch_mm"], d["tile_mm"], diameter / 2, frac, "--numpy" in sys.argv)
        print(f"  drop-cutter ({eng}) on the central period: {n}x{n} samples at {h:.4f} mm, min(made-design) {mn:+.5f} mm")
        for what, ours, theirs in (("max deviation", mx, d["max_deviation_mm"]), ("rms deviation", rms, d["rms_deviation_mm"])):
            ok = abs(ours - theirs) <= 0.01 + 0.05 * abs(theirs)
            failures += not ok
            rows.append((d["stl"], what, ours, theirs, ok))
    print(f"\n{'detail':14s} {'quantity':14s} {'ours mm':>10s} {'summary mm':>11s} {'diff mm':>9s} {'tol mm':>8s}  result")
    for stl, what, ours, theirs, ok in rows:
        print(f"{stl:14s} {what:14s} {ours:10.5f} {theirs:11.5f} {ours-theirs:+9.5f} {0.01+0.05*theirs:8.5f}  {'pass' if ok else 'FAIL'}")
    print(f"\n{'all checks passed' if failures == 0 else f'{failures} check(s) FAILED'}")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
