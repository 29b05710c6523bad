//! The members of a library, drawn from a profile: every geometry as a procedural spec (heights are
//! regenerated from it, never stored) and every distinct material as a material spec, each with a
//! readable name and its parameters. Item `k` depends only on the profile's seed and `k`, so any
//! shard can draw any item and all shards agree.

use super::profile::{GeometryFamily, LibraryProfile, MaterialFamily, Range2};
use crate::error::{Error, Result};
use crate::frame::Vec3;
use crate::material::{parse_material, Material};
use crate::rng::Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Stream offsets so geometry and material draws never share random numbers.
const GEOMETRY_STREAM: u64 = 0x4745_4f00_0000_0000;
const MATERIAL_STREAM: u64 = 0x4d41_5400_0000_0000;
const COLOUR_STREAM: u64 = 0x434f_4c00_0000_0000;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GeometryItem {
    pub index: usize,
    /// The generator family (`vgroove`, `texture`, ...).
    pub family: String,
    /// The full generator spec: `biscale forward --geometry '<spec>'` rebuilds the heights.
    pub spec: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaterialItem {
    pub index: usize,
    /// `ggx`, `merl`, ...
    pub family: String,
    /// The material spec (a MERL item's spec is its file path).
    pub spec: String,
}

/// Where item `j` of a family of `n` falls in each parameter's range: stratified (Latin
/// hypercube). Parameter `p` takes stratum `(a_p j + b_p) mod n` of `n` equal strata, with `a_p`
/// coprime to `n` (so every stratum is taken once) and `a_p / n` near a different irrational
/// for every parameter (so pairs of parameters do not line up), plus a jitter inside the
/// stratum. Every item stays a function of the seed, its family and `j` alone (shards agree),
/// and a family of 8 log-uniform Blinn exponents over [2, 2000] gets one per factor of 2.4
/// instead of random gaps.
#[derive(Debug, Clone, Copy)]
struct Strata {
    j: usize,
    n: usize,
    offset: u64,
}

impl Strata {
    fn u(&self, p: usize, jitter: f64) -> f64 {
        let n = self.n.max(1) as u64;
        // Fractional parts of sqrt(2), sqrt(3), sqrt(5), ... as multipliers.
        const IRR: [f64; 8] = [
            0.414_213_562,
            0.732_050_808,
            0.236_067_977,
            0.645_751_311,
            0.316_624_790,
            0.605_551_275,
            0.123_105_626,
            0.358_898_944,
        ];
        // Multipliers coprime to n, each differing from the earlier parameters' (and from their
        // negatives, which would reverse the same order) while the residues allow it.
        let mut used: Vec<u64> = Vec::new();
        let mut a = 1;
        for q in 0..=p {
            a = ((n as f64 * IRR[q % IRR.len()]).round() as u64).max(1);
            let ok = |a: u64| {
                gcd(a, n) == 1 && !used.iter().any(|&u| a % n == u || a % n == (n - u) % n)
            };
            let mut tries = 0;
            while !ok(a) && tries < n {
                a += 1;
                tries += 1;
            }
            while gcd(a, n) != 1 {
                a += 1;
            }
            used.push(a % n);
        }
        let b = self.offset.wrapping_mul(p as u64 + 1) % n;
        let k = (a * self.j as u64 + b) % n;
        (k as f64 + jitter) / n as f64
    }
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

fn draw(
    rng: &mut Rng,
    params: &BTreeMap<String, Range2>,
    log: &[String],
    strata: Strata,
    integer: &dyn Fn(&str) -> bool,
) -> Vec<(String, f64)> {
    params
        .iter()
        .enumerate()
        .map(|(p, (k, &[lo, hi]))| {
            let u = strata.u(p, rng.uniform());
            let v = if log.contains(k) {
                (lo.ln() + u * (hi.ln() - lo.ln())).exp()
            } else {
                lo + u * (hi - lo)
            };
            (k.clone(), rounded(k, v, integer))
        })
        .collect()
}

/// A drawn value as an item takes it: integer parameters rounded, the others to four
/// significant digits (which keep names readable and specs exact).
fn rounded(k: &str, v: f64, integer: &dyn Fn(&str) -> bool) -> f64 {
    if integer(k) {
        v.round()
    } else {
        crate::material::round_sig4(v)
    }
}

/// Every parameter at the low (`hi = false`) or the high end of its range, rounded as [`draw`]
/// rounds a draw.
fn range_end(
    params: &BTreeMap<String, Range2>,
    hi: bool,
    integer: &dyn Fn(&str) -> bool,
) -> Vec<(String, f64)> {
    params
        .iter()
        .map(|(k, &[lo, h])| (k.clone(), rounded(k, if hi { h } else { lo }, integer)))
        .collect()
}

/// Check that both ends of every family's ranges make valid items (unknown keys, values out of
/// a generator's or a model's bounds), so that a bad profile fails when it is read, naming the
/// family and the end, instead of part-way through a build.
pub fn check_range_ends(prof: &LibraryProfile) -> Result<()> {
    for (fi, fam) in prof.geometry.family.iter().enumerate() {
        let gen = crate::generators::parse_generator(&format!("{}:", fam.generator))
            .map_err(|e| e.within(format!("geometry.family[{fi}].generator")))?;
        for hi in [false, true] {
            let drawn = range_end(&fam.params, hi, &|k| gen.is_integer(k));
            let mut items = vec![format!("n={}", prof.geometry.resolution)];
            items.extend(drawn.iter().map(|(k, v)| format!("{k}={v}")));
            let spec = format!("{}:{}", fam.generator, items.join(","));
            crate::generators::parse_generator(&spec).map_err(|e| {
                e.within(format!(
                    "geometry.family[{fi}].params, every range at its {} end",
                    if hi { "high" } else { "low" }
                ))
            })?;
        }
    }
    for (fi, fam) in prof.material.family.iter().enumerate() {
        for hi in [false, true] {
            let drawn = range_end(&fam.params, hi, &|_| false);
            let mixes: &[f64] = if fam.model == "lambert" {
                &[0.0]
            } else {
                &prof.material.lambert
            };
            for &a in mixes {
                parse_material(&material_spec(fam, &drawn, a)).map_err(|e| {
                    e.within(format!(
                        "material.family[{fi}].params, every range at its {} end",
                        if hi { "high" } else { "low" }
                    ))
                })?;
            }
        }
    }
    Ok(())
}

fn png_files(dirs: &[PathBuf], base: &Path, ctx: &str) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for d in dirs {
        let d = if d.is_absolute() {
            d.clone()
        } else {
            base.join(d)
        };
        let rd = std::fs::read_dir(&d)
            .map_err(|e| Error::io(&d, "list the texture directory", e).within(ctx))?;
        for e in rd.flatten() {
            let p = e.path();
            if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")) {
                out.push(p);
            }
        }
    }
    out.sort();
    Ok(out)
}

/// Every geometry of the profile. `base` is the profile's directory (for relative texture dirs).
pub fn geometry_items(prof: &LibraryProfile, base: &Path) -> Result<Vec<GeometryItem>> {
    let mut out = Vec::with_capacity(prof.geometry_count());
    for (fi, fam) in prof.geometry.family.iter().enumerate() {
        let ctx = format!("geometry.family[{fi}]");
        let files = if fam.generator == "texture" {
            png_files(&fam.texture_dirs, base, &ctx)?
        } else {
            Vec::new()
        };
        for j in 0..fam.count {
            let index = out.len();
            let spec = geometry_spec(prof, fam, &files, j, index).map_err(|e| e.within(&ctx))?;
            out.push(GeometryItem {
                index,
                family: fam.generator.clone(),
                spec,
            });
        }
    }
    Ok(out)
}

fn geometry_spec(
    prof: &LibraryProfile,
    fam: &GeometryFamily,
    files: &[PathBuf],
    j: usize,
    index: usize,
) -> Result<String> {
    let mut rng = Rng::stream(prof.seed, GEOMETRY_STREAM + index as u64);
    let mut items = vec![format!("n={}", prof.geometry.resolution)];
    let strata = Strata {
        j,
        n: fam.count,
        offset: Rng::stream(prof.seed, GEOMETRY_STREAM + (index - j) as u64).below(1 << 31),
    };
    let gen = crate::generators::parse_generator(&format!("{}:", fam.generator))?;
    let drawn = draw(&mut rng, &fam.params, &fam.log, strata, &|k| {
        gen.is_integer(k)
    });
    let has = |k: &str| drawn.iter().any(|(kk, _)| kk == k);
    for (k, v) in &drawn {
        items.push(format!("{k}={v}"));
    }
    if gen.get("seed").is_some() && !has("seed") {
        items.push(format!("seed={}", rng.below(1 << 31)));
    }
    if fam.generator == "texture" {
        let builtins = if fam.builtin_textures {
            crate::texture::builtin_names()
        } else {
            &[]
        };
        let total = builtins.len() + files.len();
        if total == 0 {
            return Err(Error::new(
                "texture_dirs",
                "no built-in textures and no PNG files found",
            ));
        }
        let t = j % total;
        if t < builtins.len() {
            items.push(format!("tex={}", builtins[t]));
        } else {
            items.push(format!("file={}", files[t - builtins.len()].display()));
        }
        if !has("patch") {
            items.push(format!("patch={}", (j / total) % 16));
        }
    }
    let spec = format!("{}:{}", fam.generator, items.join(","));
    // Validate now, so a bad range fails before any work.
    Ok(crate::generators::parse_generator(&spec)?.name())
}

fn material_spec(fam: &MaterialFamily, drawn: &[(String, f64)], albedo: f64) -> String {
    let params: Vec<String> = drawn.iter().map(|(k, v)| format!("{k}={v}")).collect();
    let mut s = if params.is_empty() {
        fam.model.clone()
    } else {
        format!("{}:{}", fam.model, params.join(","))
    };
    if albedo > 0.0 {
        s.push_str(&format!("+lambert:albedo={albedo}"));
    }
    s
}

/// Every distinct material of the profile: each analytic draw mixed with every Lambertian albedo
/// (a `lambert` family's draws as they are), then every MERL file of the profile's directories
/// (sorted by path).
pub fn material_items(prof: &LibraryProfile, base: &Path) -> Result<Vec<MaterialItem>> {
    let mut out = Vec::new();
    for (fi, fam) in prof.material.family.iter().enumerate() {
        let ctx = format!("material.family[{fi}]");
        for j in 0..fam.count {
            let mut rng = Rng::stream(prof.seed, MATERIAL_STREAM + ((fi as u64) << 32) + j as u64);
            let strata = Strata {
                j,
                n: fam.count,
                offset: Rng::stream(prof.seed, MATERIAL_STREAM + ((fi as u64) << 32) + (1 << 31))
                    .below(1 << 31),
            };
            // Material parameters are all continuous.
            let drawn = draw(&mut rng, &fam.params, &fam.log, strata, &|_| false);
            // A Lambertian family is the matte end itself: not mixed with further albedos.
            let mixes: &[f64] = if fam.model == "lambert" {
                &[0.0]
            } else {
                &prof.material.lambert
            };
            for &a in mixes {
                let spec = material_spec(fam, &drawn, a);
                parse_material(&spec).map_err(|e| e.within(&ctx))?;
                out.push(MaterialItem {
                    index: out.len(),
                    family: fam.model.clone(),
                    spec,
                });
            }
        }
    }
    let mut merl = Vec::new();
    for d in &prof.material.merl_dirs {
        let d = if d.is_absolute() {
            d.clone()
        } else {
            base.join(d)
        };
        let rd = std::fs::read_dir(&d).map_err(|e| {
            Error::io(&d, "list the MERL directory", e).within("material.merl_dirs")
        })?;
        merl.extend(
            rd.flatten()
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|x| x == "binary")),
        );
    }
    merl.sort();
    for p in merl {
        out.push(MaterialItem {
            index: out.len(),
            family: "merl".into(),
            spec: p.display().to_string(),
        });
    }
    Ok(out)
}

/// The average RGB colour `lambda` of a material (Eq. 13): its flat-patch `fbar` averaged over a
/// fixed set of 70 direction pairs.
pub fn average_colour(mat: &Material) -> [f64; 3] {
    let pairs = crate::pairs::default_pairs(10);
    let mut s = [0.0; 3];
    for p in &pairs {
        let d = p.dirs();
        let v = mat.eval_rgb(Vec3::Z, d.wi, d.wo);
        for c in 0..3 {
            s[c] += v[c] * d.wi.z;
        }
    }
    s.map(|x| x / pairs.len() as f64)
}

/// The colour multipliers of material `index`: entry 0 is its own (`[1, 1, 1]`), then
/// `prof.material.colours` random colours with channel mean 1 (so the single-channel BRDF the
/// solvers match is unchanged; only `lambda` moves, Sec. 5.1).
pub fn colour_shifts(prof: &LibraryProfile, index: usize) -> Vec<[f32; 3]> {
    let mut rng = Rng::stream(prof.seed, COLOUR_STREAM + index as u64);
    let mut out = vec![[1.0f32; 3]];
    for _ in 0..prof.material.colours {
        let c = [
            rng.range(0.05, 1.0),
            rng.range(0.05, 1.0),
            rng.range(0.05, 1.0),
        ];
        let m = (c[0] + c[1] + c[2]) / 3.0;
        out.push([(c[0] / m) as f32, (c[1] / m) as f32, (c[2] / m) as f32]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_are_stratified_in_every_parameter_and_not_aligned() {
        for n in [1usize, 2, 8, 10, 37, 206] {
            let st = |j| Strata {
                j,
                n,
                offset: 12345,
            };
            for p in 0..3 {
                let mut seen = vec![false; n];
                for j in 0..n {
                    let k = (st(j).u(p, 0.5) * n as f64).floor() as usize;
                    assert!(!seen[k], "n {n}, parameter {p}: stratum {k} twice");
                    seen[k] = true;
                }
            }
            if n >= 8 {
                // Two parameters are not drawn in the same (or the reversed) order.
                let u0: Vec<f64> = (0..n).map(|j| st(j).u(0, 0.5)).collect();
                let u1: Vec<f64> = (0..n).map(|j| st(j).u(1, 0.5)).collect();
                let m = 0.5;
                let cov: f64 = u0.iter().zip(&u1).map(|(a, b)| (a - m) * (b - m)).sum();
                let var: f64 = u0.iter().map(|a| (a - m) * (a - m)).sum();
                assert!((cov / var).abs() < 0.5, "n {n}: correlation {}", cov / var);
            }
        }
    }

    #[test]
    fn items_are_deterministic_valid_and_named() {
        let (p, path) = LibraryProfile::load("tiny").unwrap();
        let base = path.parent().unwrap();
        let g1 = geometry_items(&p, base).unwrap();
        let g2 = geometry_items(&p, base).unwrap();
        assert_eq!(g1, g2);
        assert_eq!(g1.len(), p.geometry_count());
        for g in &g1 {
            crate::generators::parse_generator(&g.spec).unwrap();
        }
        let m = material_items(&p, base).unwrap();
        assert!(m.iter().any(|x| x.spec.contains("+lambert")));
        let c = colour_shifts(&p, 3);
        assert_eq!(c.len(), 1 + p.material.colours);
        for x in &c {
            assert!(((x[0] + x[1] + x[2]) / 3.0 - 1.0).abs() < 1e-5);
        }
    }
}
