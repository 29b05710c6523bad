//! The material spec grammar of `--material` and of scene files.
//!
//! ```text
//! material := term ('+' term)*
//! term     := model [':' key '=' value (',' key '=' value)*]  |  path-to-MERL.binary
//! ```
//! See [`MATERIAL_GRAMMAR`] for the models and keys; `biscale forward --help` prints it.

use super::{
    BlinnPhong, Distribution, Lambert, Lobe, Material, MerlBrdf, Microfacet, Shadowing, Ward,
};
use crate::error::{Error, Result};
use std::path::Path;
use std::sync::Arc;

/// Help text for the grammar, shared by `--help` and the user guide.
pub const MATERIAL_GRAMMAR: &str = "\
A material is one or more lobes joined by '+', e.g. 'ggx:alpha=0.1+lambert:albedo=0.2'.
  lambert:albedo=A              Lambertian, f = A/pi (0 <= A <= 1)
  ggx:alpha=a[,f0=F][,ks=K]     GGX, separable Smith G, Schlick F (f0=1: no Fresnel)
  beckmann:alpha=a[,f0=F][,ks=K] Beckmann, separable Smith G, Schlick F
  ct:m=m[,f0=F][,ks=K]          Cook-Torrance: Beckmann D, Schlick F, V-cavity G
  ward:alpha=a[,ks=K]           isotropic Ward
  blinn:n=N[,ks=K]              Blinn-Phong, f = K (N+8)/(8 pi) (n.h)^N
  PATH.binary                   a MERL measured BRDF (a '+' in a path is kept when the path
                                has a '/', e.g. ./gold+paint.binary)
Defaults: f0=1, ks=1. Any lobe may carry rgb=R:G:B, the material's colour (scaled to mean 1).
Roughness a, m in (0, 10]; N in [0, 1e7]; f0 in [0, 1]; ks >= 0.";

/// Split at '+' signs that start a new term: not the '+' of an exponent such as `1e+5`, nor a
/// '+' inside a file path (a term with a '/' or '\\' that does not yet end in `.binary`). A spec
/// that names an existing file as a whole is that one file, '+' signs and all.
fn split_terms(spec: &str) -> Vec<&str> {
    if spec.contains('+') && Path::new(spec.trim()).is_file() {
        return vec![spec];
    }
    let b = spec.as_bytes();
    let mut out = Vec::new();
    let mut start = 0;
    for i in 0..b.len() {
        if b[i] == b'+' {
            let prev_is_exp =
                i >= 2 && (b[i - 1] == b'e' || b[i - 1] == b'E') && b[i - 2].is_ascii_digit();
            let so_far = spec[start..i].trim();
            let inside_path =
                (so_far.contains('/') || so_far.contains('\\')) && !so_far.ends_with(".binary");
            if !prev_is_exp && !inside_path {
                out.push(&spec[start..i]);
                start = i + 1;
            }
        }
    }
    out.push(&spec[start..]);
    out
}

/// Parsed `key=value` pairs of one term, consumed as they are read so leftovers are reported.
pub(crate) struct Params<'a> {
    pub model: &'a str,
    pub pairs: Vec<(&'a str, &'a str)>,
}

impl<'a> Params<'a> {
    pub fn parse(term: &'a str) -> Result<Self> {
        let (model, rest) = match term.split_once(':') {
            Some((m, r)) => (m.trim(), r.trim()),
            None => (term.trim(), ""),
        };
        let mut pairs = Vec::new();
        if !rest.is_empty() {
            for kv in rest.split(',') {
                let Some((k, v)) = kv.split_once('=') else {
                    return Err(Error::new(
                        format!("'{term}'"),
                        format!("'{kv}' is not key=value (expected e.g. alpha=0.2)"),
                    ));
                };
                let k = k.trim();
                if pairs.iter().any(|(kk, _)| *kk == k) {
                    return Err(Error::new(
                        format!("'{term}'"),
                        format!("key '{k}' is given twice"),
                    ));
                }
                pairs.push((k, v.trim()));
            }
        }
        Ok(Params { model, pairs })
    }

    fn take(&mut self, key: &str) -> Option<&'a str> {
        let i = self.pairs.iter().position(|(k, _)| *k == key)?;
        Some(self.pairs.remove(i).1)
    }

    /// A number for `key`, `default` if absent (`None` = required), checked against `lo..=hi`.
    pub fn num(
        &mut self,
        key: &str,
        default: Option<f64>,
        lo: f64,
        hi: f64,
        lo_open: bool,
    ) -> Result<f64> {
        let model = self.model;
        let v = match self.take(key) {
            None => default.ok_or_else(|| {
                Error::new(
                    format!("'{model}'"),
                    format!("missing parameter '{key}' (e.g. {model}:{key}=...)"),
                )
            })?,
            Some(s) => s.parse::<f64>().map_err(|_| {
                Error::new(format!("'{model}'"), format!("{key}='{s}' is not a number"))
            })?,
        };
        let below = if lo_open { v <= lo } else { v < lo };
        if !v.is_finite() || below || v > hi {
            let lb = if lo_open { "(" } else { "[" };
            return Err(Error::new(
                format!("'{model}'"),
                format!(
                    "{key}={} is out of range, expected a value in {lb}{lo}, {hi}]",
                    crate::error::show_num(v)
                ),
            ));
        }
        Ok(v)
    }

    pub fn raw(&mut self, key: &str) -> Option<&'a str> {
        self.take(key)
    }

    /// Error if a key is not one the model accepts (before any is read, so that a misspelt
    /// key is reported as unknown rather than as a missing required one).
    pub fn known(&self, accepted: &str) -> Result<()> {
        match self
            .pairs
            .iter()
            .find(|(k, _)| !accepted.split(", ").any(|a| a == *k))
        {
            Some((k, _)) => Err(Error::new(
                format!("'{}'", self.model),
                format!("unknown parameter '{k}' (accepted: {accepted})"),
            )),
            None => Ok(()),
        }
    }

    /// Error if keys are left over, listing what the model accepts.
    pub fn finish(self, accepted: &str) -> Result<()> {
        if let Some((k, _)) = self.pairs.first() {
            return Err(Error::new(
                format!("'{}'", self.model),
                format!("unknown parameter '{k}' (accepted: {accepted})"),
            ));
        }
        Ok(())
    }
}

fn parse_rgb(s: &str) -> Result<[f64; 3]> {
    let parts: Vec<&str> = s.split(':').collect();
    let bad = || {
        Error::new(
            format!("rgb={s}"),
            "expected three non-negative numbers R:G:B, not all zero",
        )
    };
    if parts.len() != 3 {
        return Err(bad());
    }
    let mut c = [0.0; 3];
    for (i, p) in parts.iter().enumerate() {
        c[i] = p.trim().parse::<f64>().map_err(|_| bad())?;
        if !c[i].is_finite() || c[i] < 0.0 {
            return Err(bad());
        }
    }
    let top = c[0].max(c[1]).max(c[2]);
    if top <= 0.0 {
        return Err(bad());
    }
    // Channels so small that their mean underflows (5e-324) are taken over the largest first.
    let c = if (c[0] + c[1] + c[2]) / 3.0 > 0.0 {
        c
    } else {
        c.map(|x| x / top)
    };
    let mean = (c[0] + c[1] + c[2]) / 3.0;
    Ok([c[0] / mean, c[1] / mean, c[2] / mean])
}

fn looks_like_path(term: &str) -> bool {
    term.ends_with(".binary") || term.contains('/') || term.contains('\\')
}

/// `spec` with each term that is a file path (a MERL `.binary`) replaced by `f(term)`, the
/// other terms as they are.
pub fn map_path_terms(spec: &str, f: impl Fn(&str) -> String) -> String {
    split_terms(spec)
        .into_iter()
        .map(|t| {
            if looks_like_path(t.trim()) {
                f(t.trim())
            } else {
                t.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("+")
}

/// Keys whose value is a fraction in `[0, 1]`; the other numeric keys are positive scales.
const FRACTION_KEYS: [&str; 2] = ["f0", "albedo"];

/// The numeric parameters of the analytic terms of `spec`, in order: `(term, key, value)`, the
/// continuous handles refinement may turn (MERL terms and colours have none).
pub fn spec_params(spec: &str) -> Vec<(usize, String, f64)> {
    let mut out = Vec::new();
    for (t, term) in split_terms(spec).into_iter().enumerate() {
        let term = term.trim();
        if looks_like_path(term) {
            continue;
        }
        let Ok(p) = Params::parse(term) else { continue };
        for (k, v) in p.pairs {
            if k == "rgb" {
                continue;
            }
            if let Ok(x) = v.parse::<f64>() {
                out.push((t, k.to_string(), x));
            }
        }
    }
    out
}

/// `spec` with parameter `i` of [`spec_params`] multiplied by `factors[i]` (fractions clamped to
/// 1), written with four significant digits. Parse the result to validate it.
pub fn spec_scaled(spec: &str, factors: &[f64]) -> String {
    let params = spec_params(spec);
    let mut terms: Vec<String> = split_terms(spec)
        .iter()
        .map(|t| t.trim().to_string())
        .collect();
    for (t, term) in terms.iter_mut().enumerate() {
        let mine: Vec<(usize, &(usize, String, f64))> = params
            .iter()
            .enumerate()
            .filter(|(_, p)| p.0 == t)
            .collect();
        if mine.is_empty() {
            continue;
        }
        let Ok(p) = Params::parse(term) else { continue };
        let pairs: Vec<String> = p
            .pairs
            .iter()
            .map(|(k, v)| match mine.iter().find(|(_, q)| q.1 == *k) {
                Some((i, q)) => format!(
                    "{k}={}",
                    param_scaled(k, q.2, factors.get(*i).copied().unwrap_or(1.0))
                ),
                None => format!("{k}={v}"),
            })
            .collect();
        *term = format!("{}:{}", p.model, pairs.join(","));
    }
    terms.join("+")
}

/// Parameter `key` of value `v` multiplied by `factor`, as [`spec_scaled`] writes it: four
/// significant digits, fractions (`f0`, `albedo`) clamped to 1.
pub fn param_scaled(key: &str, v: f64, factor: f64) -> f64 {
    let x = round_sig4(v * factor);
    if FRACTION_KEYS.contains(&key) {
        x.min(1.0)
    } else {
        x
    }
}

/// `x` rounded to four significant digits: spec values that stay readable and print exactly.
pub(crate) fn round_sig4(x: f64) -> f64 {
    if x == 0.0 || !x.is_finite() {
        return x;
    }
    let m = 10f64.powi(3 - x.abs().log10().floor() as i32);
    (x * m).round() / m
}

/// Parse a material spec (see [`MATERIAL_GRAMMAR`]).
pub fn parse_material(spec: &str) -> Result<Material> {
    let ctx = |e: Error| e.within(format!("material '{spec}'"));
    if spec.trim().is_empty() {
        return Err(Error::new(
            "material",
            "empty spec; expected e.g. 'ggx:alpha=0.2'",
        ));
    }
    let mut lobes = Vec::new();
    let mut color: Option<[f64; 3]> = None;
    for term in split_terms(spec) {
        let term = term.trim();
        if term.is_empty() {
            return Err(ctx(Error::new("", "empty term around '+'")));
        }
        if looks_like_path(term) {
            let m = MerlBrdf::load(Path::new(term)).map_err(ctx)?;
            lobes.push(Lobe::Merl(Arc::new(m)));
            continue;
        }
        let mut p = Params::parse(term).map_err(ctx)?;
        if let Some(c) = p.raw("rgb") {
            if color.is_some() {
                return Err(ctx(Error::new("rgb", "the colour is given twice")));
            }
            color = Some(parse_rgb(c).map_err(ctx)?);
        }
        let lobe = match p.model {
            "lambert" => {
                p.known("albedo, rgb").map_err(ctx)?;
                let albedo = p.num("albedo", None, 0.0, 1.0, false).map_err(ctx)?;
                p.finish("albedo, rgb").map_err(ctx)?;
                Lobe::Lambert(Lambert { albedo })
            }
            "ggx" | "beckmann" => {
                if p.pairs.iter().any(|(k, _)| *k == "m") {
                    return Err(ctx(Error::new(format!("'{}'", p.model), "use alpha=..., not m (m is for ct)")));
                }
                p.known("alpha, f0, ks, rgb").map_err(ctx)?;
                let alpha = p.num("alpha", None, 0.0, 10.0, true).map_err(ctx)?;
                let f0 = p.num("f0", Some(1.0), 0.0, 1.0, false).map_err(ctx)?;
                let ks = p.num("ks", Some(1.0), 0.0, 1e6, false).map_err(ctx)?;
                let dist = if p.model == "ggx" { Distribution::Ggx } else { Distribution::Beckmann };
                p.finish("alpha, f0, ks, rgb").map_err(ctx)?;
                Lobe::Microfacet(Microfacet { dist, shadowing: Shadowing::Smith, alpha, f0, ks })
            }
            "ct" | "cooktorrance" => {
                p.known("m, f0, ks, rgb").map_err(ctx)?;
                let m = p.num("m", None, 0.0, 10.0, true).map_err(ctx)?;
                let f0 = p.num("f0", Some(1.0), 0.0, 1.0, false).map_err(ctx)?;
                let ks = p.num("ks", Some(1.0), 0.0, 1e6, false).map_err(ctx)?;
                p.finish("m, f0, ks, rgb").map_err(ctx)?;
                Lobe::Microfacet(Microfacet {
                    dist: Distribution::Beckmann,
                    shadowing: Shadowing::VCavity,
                    alpha: m,
                    f0,
                    ks,
                })
            }
            "ward" => {
                if p.pairs.iter().any(|(k, _)| *k == "ax" || *k == "ay") {
                    return Err(ctx(Error::new(
                        "'ward'",
                        "anisotropic Ward (ax, ay) is a large-scale target, not a small-scale material \
                         (small-scale materials are isotropic): use ward:alpha=...",
                    )));
                }
                p.known("alpha, ks, rgb").map_err(ctx)?;
                let alpha = p.num("alpha", None, 0.0, 10.0, true).map_err(ctx)?;
                let ks = p.num("ks", Some(1.0), 0.0, 1e6, false).map_err(ctx)?;
                p.finish("alpha, ks, rgb").map_err(ctx)?;
                Lobe::Ward(Ward { alpha, ks })
            }
            "blinn" | "phong" => {
                p.known("n, ks, rgb").map_err(ctx)?;
                let n = p.num("n", None, 0.0, 1e7, false).map_err(ctx)?;
                let ks = p.num("ks", Some(1.0), 0.0, 1e6, false).map_err(ctx)?;
                p.finish("n, ks, rgb").map_err(ctx)?;
                Lobe::Blinn(BlinnPhong { n, ks })
            }
            other => {
                return Err(ctx(Error::new(
                    format!("'{other}'"),
                    "unknown material model (expected lambert, ggx, beckmann, ct, ward, blinn, or a path to a MERL .binary)",
                )))
            }
        };
        lobes.push(lobe);
    }
    let mut m = Material::new(lobes);
    if let Some(c) = color {
        m.color = c;
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_params_scale_and_reparse() {
        let spec = "ggx:alpha=0.2684,f0=0.4571,rgb=1:0.5:0.25+lambert:albedo=0.8";
        let p = spec_params(spec);
        let keys: Vec<(usize, &str)> = p.iter().map(|(t, k, _)| (*t, k.as_str())).collect();
        assert_eq!(keys, [(0, "alpha"), (0, "f0"), (1, "albedo")]);
        assert_eq!(p[0].2, 0.2684);
        // Unit factors give back the same material; fractions are clamped to 1.
        let same = spec_scaled(spec, &[1.0, 1.0, 1.0]);
        assert_eq!(
            parse_material(&same).unwrap().spec(),
            parse_material(spec).unwrap().spec()
        );
        let s = spec_scaled(spec, &[0.5, 3.0, 2.0]);
        assert_eq!(s, "ggx:alpha=0.1342,f0=1,rgb=1:0.5:0.25+lambert:albedo=1");
        parse_material(&s).unwrap();
        assert_eq!(round_sig4(0.000123456), 0.0001235);
        assert_eq!(round_sig4(0.0), 0.0);
    }

    #[test]
    fn a_plus_in_a_merl_path_stays_in_the_path() {
        assert_eq!(
            split_terms("dir/gold+paint.binary"),
            ["dir/gold+paint.binary"]
        );
        assert_eq!(
            split_terms("dir/a.binary+lambert:albedo=0.2"),
            ["dir/a.binary", "lambert:albedo=0.2"]
        );
        assert_eq!(
            split_terms("ggx:alpha=1e+1+dir/a+b.binary+lambert:albedo=0.2"),
            ["ggx:alpha=1e+1", "dir/a+b.binary", "lambert:albedo=0.2"]
        );
        // A MERL file whose name has a '+', alone and in a sum.
        let dir = crate::testdir::TestDir::new("merl-plus");
        let p = dir.join("gold+paint.binary");
        MerlBrdf::write_synthetic(&p, |_, _, _, _| 1500.0 / std::f64::consts::PI).unwrap();
        let path = p.display().to_string();
        assert_eq!(parse_material(&path).unwrap().lobes.len(), 1);
        let sum = format!("{path}+lambert:albedo=0.2");
        assert_eq!(parse_material(&sum).unwrap().lobes.len(), 2);
    }

    #[test]
    fn parses_the_documented_examples() {
        for s in [
            "lambert:albedo=0.5",
            "ggx:alpha=0.2",
            "ggx:alpha=0.2,f0=0.9",
            "beckmann:alpha=0.3",
            "ward:alpha=0.1",
            "blinn:n=60",
            "blinn:n=1e+5",
            "ct:m=0.19,f0=0.23",
            "ggx:alpha=0.1+lambert:albedo=0.2",
            "blinn:n=60,rgb=0.9:0.6:0.3+lambert:albedo=0.3",
        ] {
            let m = parse_material(s).unwrap_or_else(|e| panic!("{s}: {e}"));
            // canonical specs parse back to the same thing
            let again = parse_material(&m.spec()).unwrap();
            assert_eq!(again.spec(), m.spec());
        }
        assert_eq!(parse_material("blinn:n=1e+5").unwrap().lobes.len(), 1);
    }

    #[test]
    fn rejects_nonsense_with_clear_messages() {
        let cases = [
            ("ggx:alpha=-0.1", "alpha=-0.1 is out of range"),
            ("ggx:alpha=nan", "out of range"),
            ("ggx", "missing parameter 'alpha'"),
            ("velvet:x=1", "unknown material model"),
            ("ggx:alpha=0.2,roughness=3", "unknown parameter 'roughness'"),
            ("ggx:alpah=0.2", "unknown parameter 'alpah'"),
            ("blinn:m=60", "unknown parameter 'm'"),
            ("ggx:alpha=abc", "is not a number"),
            ("lambert:albedo=1.5", "out of range"),
            ("ward:ax=0.3,ay=0.08", "large-scale target"),
            ("ggx:alpha=0.2+", "empty term"),
            ("missing/file.binary", "missing/file.binary"),
        ];
        for (s, want) in cases {
            let e = parse_material(s).unwrap_err().to_string();
            assert!(e.contains(want), "{s}: {e}");
            assert!(
                e.contains(s.split('+').next().unwrap_or(s)) || e.contains("material"),
                "{s}: {e}"
            );
        }
    }
}
