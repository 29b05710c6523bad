//! Procedural periodic heightfields for the geometry library (paper Sec. 5.2, Fig. 3 top row).
//!
//! A generator is named by a spec `name:key=value,key=value` (e.g. `vgroove:period=16,depth=4`,
//! `bumps:count=12,radius=10,height=4,seed=3`); keys left out take their defaults, and
//! [`Generator::name`] gives the canonical spec with every key, which parses back to the same
//! generator. Every generator makes an `n × n` heightmap (default `n = 128`) with heights in grid
//! units (one unit = the sample spacing, so the result is scale-free) and is exactly periodic: the
//! formulas are evaluated with integer phase arithmetic, so sample `x = n` would equal sample
//! `x = 0`. Where a period does not divide `n`, the number of repeats is rounded (`k =
//! round(n / period)`, at least 1) so a whole number of repeats fits; rows of bricks and threads
//! of a weave are rounded to an even count so the alternation tiles. Random generators draw only
//! from [`crate::rng::Rng`] seeded by `seed`: the same spec gives the same samples, bit for bit.
//!
//! Orientation: column index = x, row index = y; grooves run along y (heights vary with x).
//! Rotating a pattern is done elsewhere (design notes, Sec. 1).

use crate::error::{show_num, Error, Result};
use crate::heightfield::Heightfield;
use crate::material::fmt_num;
use crate::rng::Rng;
use std::f64::consts::{PI, TAU};
use std::path::Path;

/// Largest integer an `f64` holds exactly: the largest accepted seed.
const MAX_SEED: f64 = 9_007_199_254_740_992.0;

#[derive(Debug, Clone, Copy)]
enum Def {
    N(f64),
    T(&'static str),
}

#[derive(Debug, Clone, Copy)]
enum Rule {
    /// An integer in `[min, max]`.
    Int(f64, f64),
    /// A finite number `>= 0`.
    NonNeg,
    /// A finite number `> 0`.
    Positive,
    /// A length in samples, at least 2 and at most `n`.
    Period,
    /// A number in `(0, 1]`.
    Fraction,
    /// A finite number in `[min, max]`.
    Range(f64, f64),
    /// Free text (a file path or a name).
    Text,
}

#[derive(Debug, Clone, Copy)]
struct Param {
    key: &'static str,
    default: Def,
    rule: Rule,
}

const fn p(key: &'static str, default: f64, rule: Rule) -> Param {
    Param {
        key,
        default: Def::N(default),
        rule,
    }
}
const fn t(key: &'static str, default: &'static str) -> Param {
    Param {
        key,
        default: Def::T(default),
        rule: Rule::Text,
    }
}
const N: Param = p("n", 128.0, Rule::Int(4.0, 4096.0));
const SEED: Param = p("seed", 0.0, Rule::Int(0.0, MAX_SEED));

struct GenDef {
    name: &'static str,
    help: &'static str,
    params: &'static [Param],
    /// The key the relief scales with linearly (heights × s = that key × s), if any.
    amplitude: Option<&'static str>,
}

static GENS: &[GenDef] = &[
    GenDef { name: "flat", help: "a flat patch; keys: n=128", params: &[N], amplitude: None },
    GenDef {
        name: "vgroove",
        help: "symmetric V grooves along y (a pure V, no flat land); keys: n=128, period=16 (samples), depth=4",
        params: &[N, p("period", 16.0, Rule::Period), p("depth", 4.0, Rule::NonNeg)],
        amplitude: Some("depth"),
    },
    GenDef {
        name: "sine",
        help: "sinusoidal grooves along y; keys: n=128, period=16 (samples), amplitude=2 (half peak-to-peak)",
        params: &[N, p("period", 16.0, Rule::Period), p("amplitude", 2.0, Rule::NonNeg)],
        amplitude: Some("amplitude"),
    },
    GenDef {
        name: "ugroove",
        help: "rounded (half-ellipse) grooves along y between flat lands; keys: n=128, period=16, width=8 \
               (groove width, at most period), depth=4",
        params: &[
            N,
            p("period", 16.0, Rule::Period),
            p("width", 8.0, Rule::Positive),
            p("depth", 4.0, Rule::NonNeg),
        ],
        amplitude: Some("depth"),
    },
    GenDef {
        name: "bricks",
        help: "running-bond bricks with sunken mortar, vertical walls; keys: n=128, length=32 (brick length \
               along x), height=16 (row height along y), mortar=2 (joint width), depth=2 (brick relief)",
        params: &[
            N,
            p("length", 32.0, Rule::Period),
            p("height", 16.0, Rule::Period),
            p("mortar", 2.0, Rule::Positive),
            p("depth", 2.0, Rule::NonNeg),
        ],
        amplitude: Some("depth"),
    },
    GenDef {
        name: "bumps",
        help: "random smooth bumps (summed, periodic placement); keys: n=128, count=12, radius=10, height=4, seed=0",
        params: &[
            N,
            p("count", 12.0, Rule::Int(1.0, 100_000.0)),
            p("radius", 10.0, Rule::Positive),
            p("height", 4.0, Rule::NonNeg),
            SEED,
        ],
        amplitude: Some("height"),
    },
    GenDef {
        name: "dimples",
        help: "random smooth dimples (negative bumps); keys: n=128, count=12, radius=10, height=4, seed=0",
        params: &[
            N,
            p("count", 12.0, Rule::Int(1.0, 100_000.0)),
            p("radius", 10.0, Rule::Positive),
            p("height", 4.0, Rule::NonNeg),
            SEED,
        ],
        amplitude: Some("height"),
    },
    GenDef {
        name: "pyramids",
        help: "square pyramids in a grid; keys: n=128, period=16 (base side), height=4",
        params: &[N, p("period", 16.0, Rule::Period), p("height", 4.0, Rule::NonNeg)],
        amplitude: Some("height"),
    },
    GenDef {
        name: "weave",
        help: "plain weave of round threads over/under; keys: n=128, period=16 (thread spacing), height=4",
        params: &[N, p("period", 16.0, Rule::Period), p("height", 4.0, Rule::NonNeg)],
        amplitude: Some("height"),
    },
    GenDef {
        name: "fbm",
        help: "periodic gradient-noise fBm, peak |z| = amplitude; keys: n=128, cells=4 (lattice cells of the \
               first octave), octaves=5, persistence=0.5, lacunarity=2, amplitude=4, seed=0",
        params: &[
            N,
            p("cells", 4.0, Rule::Int(1.0, 4096.0)),
            p("octaves", 5.0, Rule::Int(1.0, 16.0)),
            p("persistence", 0.5, Rule::Fraction),
            p("lacunarity", 2.0, Rule::Range(1.5, 8.0)),
            p("amplitude", 4.0, Rule::NonNeg),
            SEED,
        ],
        amplitude: Some("amplitude"),
    },
    GenDef {
        name: "brushed",
        help: "random grooves along y whose facet slopes along x are exactly Gaussian (a brushed or sanded \
               finish: it widens a lobe along x by that slope spread); keys: n=128, slope=0.2 (RMS slope along x), \
               slope_y=0 (RMS slope of an independent profile along y; > 0 spreads both ways), kmin=2, kmax=12 \
               (band of the random profile, cycles per patch; kmax at most n/2), seed=0",
        params: &[
            N,
            p("slope", 0.2, Rule::Range(0.0, 10.0)),
            p("slope_y", 0.0, Rule::Range(0.0, 10.0)),
            p("kmin", 2.0, Rule::Int(1.0, 1024.0)),
            p("kmax", 12.0, Rule::Int(1.0, 1024.0)),
            SEED,
        ],
        amplitude: Some("slope"),
    },
    GenDef {
        name: "texture",
        help: "height patch from an image by the paper's recipe (grey, 4n×4n, patch of a 4×4 grid, FFT high-pass, \
               histogram equalisation); keys: n=128, tex=cells (built-in texture) or file=PATH (a PNG), \
               patch=0 (0..15, row-major), amplitude=4, cutoff=4 (cycles per patch), seed=0 (built-ins)",
        params: &[
            N,
            t("tex", "cells"),
            t("file", ""),
            p("patch", 0.0, Rule::Int(0.0, 15.0)),
            p("amplitude", 4.0, Rule::NonNeg),
            p("cutoff", 4.0, Rule::NonNeg),
            SEED,
        ],
        amplitude: Some("amplitude"),
    },
];

/// A parameter value.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Num(f64),
    Text(String),
}

/// A parsed, validated procedural generator: its kind and every parameter.
#[derive(Debug, Clone, PartialEq)]
pub struct Generator {
    kind: usize,
    values: Vec<Value>,
}

/// Every generator name with a one-line help naming its keys and defaults (for `--help`).
pub fn list() -> Vec<(&'static str, &'static str)> {
    GENS.iter().map(|g| (g.name, g.help)).collect()
}

fn known_names() -> String {
    GENS.iter().map(|g| g.name).collect::<Vec<_>>().join(", ")
}

/// Parse and validate a spec `name:key=value,...`. Errors name the spec and the key.
/// `spec` with `f` applied to the path of its `file=PATH` key (a texture generator's image), the
/// rest unchanged; a spec without that key comes back as it is. Scenes use it to resolve the
/// path against the scene file's directory.
pub fn map_file_key(spec: &str, f: impl Fn(&str) -> String) -> String {
    match spec.split_once(':') {
        Some((head, rest)) if rest.split(',').any(|kv| kv.trim().starts_with("file=")) => {
            let items: Vec<String> = rest
                .split(',')
                .map(|kv| match kv.trim().strip_prefix("file=") {
                    Some(p) => format!("file={}", f(p)),
                    None => kv.to_string(),
                })
                .collect();
            format!("{head}:{}", items.join(","))
        }
        _ => spec.to_string(),
    }
}

pub fn parse_generator(spec: &str) -> Result<Generator> {
    let ctx = spec.trim();
    let (name, rest) = match ctx.split_once(':') {
        Some((a, b)) => (a.trim(), b),
        None => (ctx, ""),
    };
    let lname = name.to_ascii_lowercase();
    let kind = GENS.iter().position(|g| g.name == lname).ok_or_else(|| {
        Error::new(
            ctx,
            format!(
                "unknown geometry generator '{name}' (expected one of: {})",
                known_names()
            ),
        )
    })?;
    let def = &GENS[kind];
    let mut values: Vec<Option<Value>> = vec![None; def.params.len()];
    for item in rest.split(',') {
        let item = item.trim();
        if item.is_empty() {
            continue;
        }
        let (key, val) = item.split_once('=').ok_or_else(|| {
            Error::new(
                ctx,
                format!(
                    "'{item}' is not of the form key=value (keys of {}: {})",
                    def.name,
                    keys_of(def)
                ),
            )
        })?;
        let key = key.trim().to_ascii_lowercase();
        let val = val.trim();
        let idx = def
            .params
            .iter()
            .position(|p| p.key == key)
            .ok_or_else(|| {
                Error::new(
                    ctx,
                    format!(
                        "unknown key '{key}' for {} (accepted keys: {})",
                        def.name,
                        keys_of(def)
                    ),
                )
            })?;
        if values[idx].is_some() {
            return Err(Error::new(ctx, format!("key '{key}' is given twice")));
        }
        let prm = def.params[idx];
        values[idx] = Some(match prm.rule {
            Rule::Text if val.is_empty() => {
                return Err(Error::new(
                    ctx,
                    format!("key '{key}' has no value; expected one (or leave the key out)"),
                ))
            }
            Rule::Text => Value::Text(val.to_string()),
            _ => {
                let v: f64 = val.parse().map_err(|_| {
                    Error::new(ctx, format!("key '{key}': '{val}' is not a number"))
                })?;
                Value::Num(v)
            }
        });
    }
    // texture: tex and file are alternatives.
    if def.name == "texture" {
        let given = |k: &str| {
            def.params
                .iter()
                .position(|p| p.key == k)
                .and_then(|i| values[i].as_ref())
                .map(|v| !matches!(v, Value::Text(s) if s.is_empty()))
                .unwrap_or(false)
        };
        if given("tex") && given("file") {
            return Err(Error::new(
                ctx,
                "give either tex=NAME (a built-in texture) or file=PATH, not both",
            ));
        }
    }
    let values: Vec<Value> = values
        .into_iter()
        .zip(def.params)
        .map(|(v, p)| {
            v.unwrap_or(match p.default {
                Def::N(x) => Value::Num(x),
                Def::T(s) => Value::Text(s.to_string()),
            })
        })
        .collect();
    let g = Generator { kind, values };
    g.validate(ctx)?;
    Ok(g)
}

fn keys_of(def: &GenDef) -> String {
    def.params
        .iter()
        .map(|p| p.key)
        .collect::<Vec<_>>()
        .join(", ")
}

impl Generator {
    /// The generator's kind, e.g. `"vgroove"`.
    pub fn kind(&self) -> &'static str {
        GENS[self.kind].name
    }

    /// Resolution: the heightmap is `n × n`.
    pub fn n(&self) -> usize {
        self.num("n") as usize
    }

    /// A numeric parameter by key (`None` for unknown or text keys).
    pub fn get(&self, key: &str) -> Option<f64> {
        let i = GENS[self.kind].params.iter().position(|p| p.key == key)?;
        match &self.values[i] {
            Value::Num(v) => Some(*v),
            Value::Text(_) => None,
        }
    }

    /// The continuous shape parameters refinement may vary, with their values: numeric and
    /// non-zero, not integers (counts, band limits, seeds, `n`), and not the amplitude key, which
    /// a relief scale covers.
    pub fn shape_params(&self) -> Vec<(&'static str, f64)> {
        let def = &GENS[self.kind];
        def.params
            .iter()
            .zip(&self.values)
            .filter_map(|(p, v)| match v {
                Value::Num(x)
                    if *x != 0.0
                        && !matches!(p.rule, Rule::Int(..))
                        && Some(p.key) != def.amplitude =>
                {
                    Some((p.key, *x))
                }
                _ => None,
            })
            .collect()
    }

    /// Whether `key` takes integers only (counts, seeds, band limits): library draws round it.
    pub fn is_integer(&self, key: &str) -> bool {
        GENS[self.kind]
            .params
            .iter()
            .any(|p| p.key == key && matches!(p.rule, Rule::Int(..)))
    }

    /// A copy with `key` set to `value` (text as it would appear in a spec), validated.
    pub fn with_param(&self, key: &str, value: &str) -> Result<Generator> {
        let def = &GENS[self.kind];
        let mut items = Vec::new();
        for (p, v) in def.params.iter().zip(&self.values) {
            if p.key == key {
                continue;
            }
            if let Some(s) = self.item(p, v) {
                items.push(s);
            }
        }
        items.push(format!("{key}={value}"));
        if def.name == "texture" && key == "file" {
            items.retain(|s| !s.starts_with("tex="));
        }
        if def.name == "texture" && key == "tex" {
            items.retain(|s| !s.starts_with("file="));
        }
        parse_generator(&format!("{}:{}", def.name, items.join(",")))
    }

    fn item(&self, p: &Param, v: &Value) -> Option<String> {
        match v {
            Value::Num(x) => Some(format!("{}={}", p.key, fmt_num(*x))),
            Value::Text(s) => {
                // texture: only one of tex / file is written.
                if self.kind() == "texture" {
                    let file_set = !self.text("file").is_empty();
                    if (p.key == "tex" && file_set) || (p.key == "file" && !file_set) {
                        return None;
                    }
                }
                Some(format!("{}={s}", p.key))
            }
        }
    }

    /// The canonical spec with every parameter; parsing it gives back an equal generator.
    pub fn name(&self) -> String {
        let def = &GENS[self.kind];
        let items: Vec<String> = def
            .params
            .iter()
            .zip(&self.values)
            .filter_map(|(p, v)| self.item(p, v))
            .collect();
        format!("{}:{}", def.name, items.join(","))
    }

    fn num(&self, key: &str) -> f64 {
        self.get(key).unwrap_or(0.0)
    }

    fn text(&self, key: &str) -> &str {
        let def = &GENS[self.kind];
        match def
            .params
            .iter()
            .position(|p| p.key == key)
            .map(|i| &self.values[i])
        {
            Some(Value::Text(s)) => s,
            _ => "",
        }
    }

    fn validate(&self, ctx: &str) -> Result<()> {
        let def = &GENS[self.kind];
        let n = self.get("n").unwrap_or(128.0);
        for (p, v) in def.params.iter().zip(&self.values) {
            let Value::Num(x) = v else { continue };
            let x = *x;
            let key = p.key;
            let err = |what: String| {
                Err(Error::new(
                    ctx,
                    format!("key '{key}': {what}, got {}", show_num(x)),
                ))
            };
            if !x.is_finite() {
                return err("expected a finite number".into());
            }
            match p.rule {
                Rule::Int(lo, hi) => {
                    if x.fract() != 0.0 || x < lo || x > hi {
                        return err(format!("expected an integer from {lo} to {hi}"));
                    }
                }
                Rule::NonNeg => {
                    if x < 0.0 {
                        return err("expected a size >= 0".into());
                    }
                }
                Rule::Positive => {
                    if x <= 0.0 {
                        return err("expected a size > 0".into());
                    }
                }
                Rule::Period => {
                    if x < 2.0 {
                        return err("expected at least 2 samples".into());
                    }
                    if x > n {
                        return err(format!("expected at most n = {} samples", show_num(n)));
                    }
                }
                Rule::Fraction => {
                    if !(x > 0.0 && x <= 1.0) {
                        return err("expected a number in (0, 1]".into());
                    }
                }
                Rule::Range(lo, hi) => {
                    if x < lo || x > hi {
                        return err(format!("expected a number from {lo} to {hi}"));
                    }
                }
                Rule::Text => {}
            }
        }
        let cross = |key: &str, what: String| Err(Error::new(ctx, format!("key '{key}': {what}")));
        match def.name {
            "ugroove" if self.num("width") > self.num("period") => {
                return cross(
                    "width",
                    format!(
                        "groove width {} exceeds the period {}",
                        self.num("width"),
                        self.num("period")
                    ),
                );
            }
            "bricks" => {
                let m = self.num("mortar");
                let lim = self.num("length").min(self.num("height"));
                if m >= lim {
                    return cross(
                        "mortar",
                        format!(
                            "mortar width {m} must be below the brick length and height ({lim})"
                        ),
                    );
                }
            }
            "bumps" | "dimples" if self.num("radius") > n => {
                return cross(
                    "radius",
                    format!(
                        "radius {} must be at most n = {n}",
                        show_num(self.num("radius"))
                    ),
                );
            }
            "fbm" if self.num("cells") > n / 2.0 => {
                return cross(
                    "cells",
                    format!(
                        "{} lattice cells exceed n/2 = {} (Nyquist)",
                        self.num("cells"),
                        n / 2.0
                    ),
                );
            }
            "brushed" => {
                let (k0, k1) = (self.num("kmin"), self.num("kmax"));
                if k0 > k1 {
                    return cross("kmin", format!("kmin {k0} must be at most kmax {k1}"));
                }
                if k1 > n / 2.0 {
                    return cross(
                        "kmax",
                        format!("kmax {k1} exceeds n/2 = {} (Nyquist)", n / 2.0),
                    );
                }
            }
            "texture" => {
                if self.num("cutoff") > n / 2.0 {
                    return cross(
                        "cutoff",
                        format!(
                            "cutoff {} exceeds n/2 = {}",
                            show_num(self.num("cutoff")),
                            n / 2.0
                        ),
                    );
                }
                if 4.0 * n > 4096.0 {
                    return cross(
                        "n",
                        format!(
                            "texture patches are at most 1024 samples (the image is 4n), got {n}"
                        ),
                    );
                }
                if self.text("file").is_empty() {
                    let tex = self.text("tex");
                    if !crate::texture::builtin_names().contains(&tex) {
                        return cross(
                            "tex",
                            format!(
                                "unknown built-in texture '{tex}' (expected one of: {}), or give file=PATH",
                                crate::texture::builtin_names().join(", ")
                            ),
                        );
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// Make the heightfield (`n × n`, grid units, `cell_mm = 1`, named by the canonical spec).
    pub fn build(&self) -> Result<Heightfield> {
        let n = self.n();
        let name = self.name();
        let z = match self.kind() {
            "flat" => vec![0.0; n * n],
            "vgroove" => {
                let d = self.num("depth");
                profile_x(n, self.num("period"), |t, _| {
                    -d * (1.0 - (2.0 * t - 1.0).abs())
                })
            }
            "sine" => {
                let a = self.num("amplitude");
                profile_x(n, self.num("period"), |t, _| a * (TAU * t).sin())
            }
            "ugroove" => {
                let (w, d) = (self.num("width"), self.num("depth"));
                profile_x(n, self.num("period"), |t, pw| {
                    let w = w.min(pw);
                    let s = (t - 0.5) * pw;
                    let q = 2.0 * s / w;
                    if q.abs() < 1.0 {
                        -d * (1.0 - q * q).sqrt()
                    } else {
                        0.0
                    }
                })
            }
            "bricks" => bricks(
                n,
                self.num("length"),
                self.num("height"),
                self.num("mortar"),
                self.num("depth"),
            ),
            "bumps" => bumps(
                n,
                self.num("count") as usize,
                self.num("radius"),
                self.num("height"),
                self.seed(),
            ),
            "dimples" => bumps(
                n,
                self.num("count") as usize,
                self.num("radius"),
                -self.num("height"),
                self.seed(),
            ),
            "pyramids" => pyramids(n, self.num("period"), self.num("height")),
            "brushed" => {
                let band = (self.num("kmin") as usize, self.num("kmax") as usize);
                let px = gaussian_slope_profile(n, self.num("slope"), band, self.seed(), 0);
                let py = gaussian_slope_profile(n, self.num("slope_y"), band, self.seed(), 1);
                (0..n * n).map(|i| px[i % n] + py[i / n]).collect()
            }
            "weave" => weave(n, self.num("period"), self.num("height")),
            "fbm" => {
                let mut v = fbm_window(
                    n,
                    self.num("cells") as usize,
                    self.num("octaves") as usize,
                    self.num("persistence"),
                    self.num("lacunarity"),
                    self.seed(),
                    Window::full(n),
                );
                let peak = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                let s = if peak > 0.0 {
                    self.num("amplitude") / peak
                } else {
                    0.0
                };
                v.iter_mut().for_each(|x| *x *= s);
                v
            }
            "texture" => {
                let file = self.text("file");
                let (patch, amplitude, cutoff) = (
                    self.num("patch") as usize,
                    self.num("amplitude"),
                    self.num("cutoff"),
                );
                if file.is_empty() {
                    crate::texture::builtin_patch_heights(
                        self.text("tex"),
                        self.seed(),
                        patch,
                        amplitude,
                        cutoff,
                        n,
                    )
                } else {
                    let img = crate::texture::load_grey(Path::new(file))?;
                    crate::texture::patch_heights_sized(&img, patch, amplitude, cutoff, n)
                }
                .map_err(|e| e.within(&name))?
            }
            other => {
                return Err(Error::new(
                    &name,
                    format!("generator '{other}' has no builder"),
                ))
            }
        };
        Heightfield::new(n, n, z, 1.0, name)
    }

    fn seed(&self) -> u64 {
        self.num("seed") as u64
    }
}

/// Number of whole repeats of `period` samples in `n` (at least 1).
fn repeats(n: usize, period: f64) -> usize {
    ((n as f64 / period).round() as usize).max(1)
}

/// A profile varying with x only: `f(t, pw)` with `t` the phase in `[0, 1)` of an integer number of
/// repeats and `pw` the effective period in samples.
fn profile_x(n: usize, period: f64, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
    let k = repeats(n, period);
    let pw = n as f64 / k as f64;
    let row: Vec<f64> = (0..n)
        .map(|x| f(((x * k) % n) as f64 / n as f64, pw))
        .collect();
    let mut z = Vec::with_capacity(n * n);
    for _ in 0..n {
        z.extend_from_slice(&row);
    }
    z
}

fn bricks(n: usize, length: f64, height: f64, mortar: f64, depth: f64) -> Vec<f64> {
    let kx = repeats(n, length);
    let ky = (2 * ((n as f64 / (2.0 * height)).round() as usize)).max(2);
    let mut z = vec![0.0; n * n];
    for y in 0..n {
        let row = (y * ky) / n;
        let v = ((y * ky) % n) as f64 / ky as f64; // samples into the row
        let shift = if row % 2 == 1 { n } else { 0 };
        for x in 0..n {
            let u = ((2 * kx * x + shift) % (2 * n)) as f64 / (2 * kx) as f64; // samples into the brick
            let joint = u < mortar || v < mortar;
            z[y * n + x] = if joint { 0.0 } else { depth };
        }
    }
    z
}

fn bumps(n: usize, count: usize, radius: f64, height: f64, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    let mut z = vec![0.0; n * n];
    let r2 = radius * radius;
    let ni = n as i64;
    for _ in 0..count {
        let cx = rng.range(0.0, n as f64);
        let cy = rng.range(0.0, n as f64);
        let (x0, x1) = ((cx - radius).floor() as i64, (cx + radius).ceil() as i64);
        let (y0, y1) = ((cy - radius).floor() as i64, (cy + radius).ceil() as i64);
        for y in y0..=y1 {
            let dy = y as f64 - cy;
            let yi = y.rem_euclid(ni) as usize;
            for x in x0..=x1 {
                let dx = x as f64 - cx;
                let q = (dx * dx + dy * dy) / r2;
                if q < 1.0 {
                    let xi = x.rem_euclid(ni) as usize;
                    z[yi * n + xi] += height * (1.0 - q) * (1.0 - q);
                }
            }
        }
    }
    z
}

fn pyramids(n: usize, period: f64, height: f64) -> Vec<f64> {
    let k = repeats(n, period);
    let ph: Vec<f64> = (0..n)
        .map(|x| (2.0 * (((x * k) % n) as f64 / n as f64) - 1.0).abs())
        .collect();
    let mut z = vec![0.0; n * n];
    for y in 0..n {
        for x in 0..n {
            z[y * n + x] = height * (1.0 - ph[x].max(ph[y]));
        }
    }
    z
}

fn weave(n: usize, period: f64, height: f64) -> Vec<f64> {
    // An even number of threads so that over/under alternation tiles.
    let k = (2 * ((n as f64 / (2.0 * period)).round() as usize)).max(2);
    // Thread coordinate of sample x: integer part i, fraction f.
    let coord: Vec<(usize, f64)> = (0..n)
        .map(|x| ((x * k) / n, ((x * k) % n) as f64 / n as f64))
        .collect();
    let bulge = |f: f64| 0.5 * (1.0 - (2.0 * f - 1.0).powi(2)).max(0.0).sqrt();
    let mut z = vec![0.0; n * n];
    for y in 0..n {
        let (j, fy) = coord[y];
        for x in 0..n {
            let (i, fx) = coord[x];
            // Warp thread i runs along y, over weft j when i + j is even.
            let warp = 0.5 * (PI * (fy - 0.5 + (i + j) as f64)).cos() + bulge(fx);
            let weft = -0.5 * (PI * (fx - 0.5 + (i + j) as f64)).cos() + bulge(fy);
            z[y * n + x] = height * warp.max(weft);
        }
    }
    z
}

/// Periodic 2-D gradient (Perlin) noise on a `period × period` lattice with random unit gradients.
pub(crate) struct PeriodicNoise {
    period: usize,
    grads: Vec<(f64, f64)>,
}

impl PeriodicNoise {
    pub(crate) fn new(period: usize, rng: &mut Rng) -> Self {
        let period = period.max(1);
        let grads = (0..period * period)
            .map(|_| {
                let a = rng.range(0.0, TAU);
                (a.cos(), a.sin())
            })
            .collect();
        PeriodicNoise { period, grads }
    }

    /// Noise at lattice coordinates `(ix + fx, iy + fy)`, `fx, fy` in `[0, 1)`; periodic in `ix, iy`.
    pub(crate) fn eval_split(&self, ix: usize, fx: f64, iy: usize, fy: f64) -> f64 {
        let p = self.period;
        let (x0, y0) = (ix % p, iy % p);
        let (x1, y1) = ((x0 + 1) % p, (y0 + 1) % p);
        let g = |x: usize, y: usize, dx: f64, dy: f64| {
            let (gx, gy) = self.grads[y * p + x];
            gx * dx + gy * dy
        };
        let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
        let (u, v) = (fade(fx), fade(fy));
        let a = g(x0, y0, fx, fy) + u * (g(x1, y0, fx - 1.0, fy) - g(x0, y0, fx, fy));
        let b =
            g(x0, y1, fx, fy - 1.0) + u * (g(x1, y1, fx - 1.0, fy - 1.0) - g(x0, y1, fx, fy - 1.0));
        a + v * (b - a)
    }

    /// Noise at `(x, y)` in `[0, 1)²` of the period (any real; wrapped).
    pub(crate) fn eval(&self, x: f64, y: f64) -> f64 {
        let p = self.period as f64;
        let (u, v) = ((x * p).rem_euclid(p), (y * p).rem_euclid(p));
        let (iu, iv) = (u.floor(), v.floor());
        self.eval_split(iu as usize, u - iu, iv as usize, v - iv)
    }
}

/// A periodic profile of `n` samples whose `n` slopes (`p[x + 1] - p[x]`, wrapping) are the
/// Gaussian quantiles `Φ⁻¹((r + ½) / n)` scaled to RMS `slope` exactly, in the order of the slopes
/// of a band-limited random profile (cosines of cycles `band.0..=band.1` per patch, random phases,
/// amplitudes `1/k` so every cycle adds the same slope). The rank mapping keeps that profile's
/// shape and makes the slope histogram Gaussian, so the facets' normal distribution is the
/// Beckmann-like spread a rough finish has, with no tails and no peaks at the extremes (a sine's
/// slopes pile up at its steepest). Quantiles are antisymmetric, so the slopes sum to zero and the
/// profile closes on itself. Heights have zero mean. Substream `stream` of `seed`.
fn gaussian_slope_profile(
    n: usize,
    slope: f64,
    band: (usize, usize),
    seed: u64,
    stream: u64,
) -> Vec<f64> {
    if slope == 0.0 {
        return vec![0.0; n];
    }
    let mut rng = Rng::stream(seed, stream);
    let mut shape = vec![0.0; n];
    for k in band.0..=band.1 {
        let phase = rng.uniform() * TAU;
        let a = 1.0 / k as f64;
        for (x, v) in shape.iter_mut().enumerate() {
            *v += a * (TAU * (k * x % n) as f64 / n as f64 + phase).cos();
        }
    }
    let d: Vec<f64> = (0..n).map(|x| shape[(x + 1) % n] - shape[x]).collect();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| d[a].total_cmp(&d[b]).then(a.cmp(&b)));
    // Quantiles of the lower half, mirrored: q[n - 1 - r] = -q[r] exactly.
    let mut q = vec![0.0; n];
    for r in 0..n / 2 {
        q[r] = normal_quantile((r as f64 + 0.5) / n as f64);
        q[n - 1 - r] = -q[r];
    }
    let rms = (q.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
    let mut slopes = vec![0.0; n];
    for (r, &x) in order.iter().enumerate() {
        slopes[x] = slope * q[r] / rms;
    }
    let mut p = Vec::with_capacity(n);
    let mut h = 0.0;
    for s in &slopes {
        p.push(h);
        h += s;
    }
    let mean = p.iter().sum::<f64>() / n as f64;
    p.iter_mut().for_each(|v| *v -= mean);
    p
}

/// The standard normal quantile `Φ⁻¹(p)` for `p` in `(0, 1)`, by Acklam's rational approximation
/// (relative error below 1.2e-9), exactly antisymmetric about `p = ½`.
fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969683028665376e+01,
        2.209460984245205e+02,
        -2.759285104469687e+02,
        1.38357751867269e+02,
        -3.066479806614716e+01,
        2.506628277459239e+00,
    ];
    const B: [f64; 5] = [
        -5.447609879822406e+01,
        1.615858368580409e+02,
        -1.556989798598866e+02,
        6.680131188771972e+01,
        -1.328068155288572e+01,
    ];
    const C: [f64; 6] = [
        -7.784894002430293e-03,
        -3.223964580411365e-01,
        -2.400758277161838e+00,
        -2.549732539343734e+00,
        4.374664141464968e+00,
        2.938163982698783e+00,
    ];
    const D: [f64; 4] = [
        7.784695709041462e-03,
        3.224671290700398e-01,
        2.445134137142996e+00,
        3.754408661907416e+00,
    ];
    if p > 0.5 {
        return -normal_quantile(1.0 - p);
    }
    if p < 0.02425 {
        let q = (-2.0 * p.ln()).sqrt();
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// A rectangle of samples `x0..x0 + w` × `y0..y0 + h` of an `n × n` field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Window {
    pub x0: usize,
    pub y0: usize,
    pub w: usize,
    pub h: usize,
}

impl Window {
    pub(crate) fn full(n: usize) -> Self {
        Window {
            x0: 0,
            y0: 0,
            w: n,
            h: n,
        }
    }

    /// The field coordinates `(x, y)` of the window's samples, row-major.
    pub(crate) fn samples(self) -> impl Iterator<Item = (usize, usize)> {
        (self.y0..self.y0 + self.h)
            .flat_map(move |y| (self.x0..self.x0 + self.w).map(move |x| (x, y)))
    }

    /// Index in the window of field sample `(x, y)`, if inside.
    pub(crate) fn index(self, x: usize, y: usize) -> Option<usize> {
        (x >= self.x0 && x < self.x0 + self.w && y >= self.y0 && y < self.y0 + self.h)
            .then(|| (y - self.y0) * self.w + (x - self.x0))
    }
}

/// Periodic fBm on an `n × n` grid: octave `o` has `round(cells · lacunarity^o)` lattice cells
/// (octaves finer than one cell per sample are skipped) and weight `persistence^o`. Not normalised.
/// Only the samples inside `win` are computed (a texture patch reads a sixteenth of its image),
/// each exactly as the whole field ([`Window::full`]) computes it.
pub(crate) fn fbm_window(
    n: usize,
    cells: usize,
    octaves: usize,
    persistence: f64,
    lacunarity: f64,
    seed: u64,
    win: Window,
) -> Vec<f64> {
    let mut z = vec![0.0; win.w * win.h];
    let mut amp = 1.0;
    for o in 0..octaves {
        let per = (cells as f64 * lacunarity.powi(o as i32)).round() as usize;
        if per == 0 || per > n {
            break;
        }
        let mut rng = Rng::stream(seed, o as u64);
        let noise = PeriodicNoise::new(per, &mut rng);
        let coord = |x: usize| ((x * per) / n, ((x * per) % n) as f64 / n as f64);
        let xs: Vec<(usize, f64)> = (win.x0..win.x0 + win.w).map(coord).collect();
        for (row, y) in z.chunks_mut(win.w.max(1)).zip(win.y0..) {
            let (iy, fy) = coord(y);
            for (zi, &(ix, fx)) in row.iter_mut().zip(&xs) {
                *zi += amp * noise.eval_split(ix, fx, iy, fy);
            }
        }
        amp *= persistence;
    }
    z
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Largest neighbour difference inside the period (no wrap) and across the seams.
    fn jumps(hf: &Heightfield) -> (f64, f64) {
        let (w, h) = (hf.width() as i64, hf.height() as i64);
        let (mut inner, mut seam) = (0.0f64, 0.0f64);
        for y in 0..h {
            for x in 0..w {
                let dx = (hf.at(x + 1, y) - hf.at(x, y)).abs();
                let dy = (hf.at(x, y + 1) - hf.at(x, y)).abs();
                if x + 1 < w {
                    inner = inner.max(dx);
                } else {
                    seam = seam.max(dx);
                }
                if y + 1 < h {
                    inner = inner.max(dy);
                } else {
                    seam = seam.max(dy);
                }
            }
        }
        (inner, seam)
    }

    const SPECS: &[&str] = &[
        "flat:n=16",
        "vgroove:period=16,depth=4",
        "vgroove:n=100,period=7,depth=3",
        "sine:n=64,period=10,amplitude=2",
        "ugroove:n=96,period=20,width=12,depth=5",
        "bricks:n=128,length=30,height=13,mortar=2,depth=2",
        "bumps:count=12,radius=10,height=4,seed=3",
        "bumps:n=64,count=5,radius=40,height=1,seed=1",
        "dimples:n=64,count=30,radius=6,height=2,seed=9",
        "pyramids:n=90,period=16,height=4",
        "weave:n=128,period=12,height=3",
        "fbm:n=128,octaves=6,seed=5",
        "fbm:n=64,cells=3,lacunarity=2.5,persistence=0.7,amplitude=1,seed=2",
        "texture:n=64,tex=cells,patch=5,amplitude=3",
        "brushed:n=64,slope=0.3,seed=4",
        "brushed:n=100,slope=0.2,slope_y=0.1,kmin=1,kmax=25,seed=2",
    ];

    #[test]
    fn file_key_of_a_texture_spec_is_mapped_and_nothing_else() {
        let f = |p: &str| format!("/scene/{p}");
        assert_eq!(
            map_file_key("texture:file=wood.png,patch=1", f),
            "texture:file=/scene/wood.png,patch=1"
        );
        assert_eq!(map_file_key("texture:tex=cells", f), "texture:tex=cells");
        assert_eq!(map_file_key("bumps:n=32", f), "bumps:n=32");
        assert_eq!(map_file_key("wood.png", f), "wood.png");
    }

    #[test]
    fn every_generator_builds_is_periodic_and_deterministic() {
        let mut kinds = std::collections::BTreeSet::new();
        for spec in SPECS {
            let g = parse_generator(spec).unwrap();
            kinds.insert(g.kind());
            let a = g.build().unwrap();
            assert_eq!(a.width(), g.n());
            assert_eq!(a.height(), g.n());
            let (inner, seam) = jumps(&a);
            assert!(
                seam <= inner + 1e-9,
                "{spec}: seam jump {seam} > largest inner jump {inner}"
            );
            let b = parse_generator(&g.name()).unwrap().build().unwrap();
            let bits =
                |h: &Heightfield| h.samples().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a), bits(&b), "{spec} is not deterministic");
            if g.kind() != "flat" {
                let (lo, hi) = a.min_max();
                assert!(hi > lo, "{spec} is flat");
            }
        }
        for (name, _) in list() {
            assert!(kinds.contains(name), "generator {name} untested");
        }
    }

    #[test]
    fn smooth_generators_have_small_seam_jumps() {
        // For continuous profiles the seam step is no larger than the steepest sampled step.
        let g = parse_generator("sine:n=64,period=16,amplitude=2")
            .unwrap()
            .build()
            .unwrap();
        assert!((g.at(64, 3) - g.at(0, 3)).abs() == 0.0);
        let v = parse_generator("vgroove:n=64,period=16,depth=4")
            .unwrap()
            .build()
            .unwrap();
        assert_eq!(v.at(0, 0), 0.0);
        assert_eq!(v.at(8, 0), -4.0);
        assert_eq!(v.min_max(), (-4.0, 0.0));
    }

    #[test]
    fn random_generators_depend_on_the_seed() {
        for base in [
            "bumps:n=64,count=8,radius=6",
            "dimples:n=64",
            "fbm:n=64",
            "texture:n=32,tex=marble",
            "brushed:n=64",
        ] {
            let a = parse_generator(&format!("{base},seed=1"))
                .unwrap()
                .build()
                .unwrap();
            let b = parse_generator(&format!("{base},seed=2"))
                .unwrap()
                .build()
                .unwrap();
            assert_ne!(a.samples(), b.samples(), "{base}");
        }
        let d = parse_generator("dimples:n=64,seed=4")
            .unwrap()
            .build()
            .unwrap();
        assert!(d.min_max().1 <= 0.0 && d.min_max().0 < 0.0);
        let f = parse_generator("fbm:n=64,amplitude=2.5")
            .unwrap()
            .build()
            .unwrap();
        let peak = f.samples().iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!((peak - 2.5).abs() < 1e-12);
    }

    #[test]
    fn brushed_slopes_are_gaussian_quantiles_of_the_asked_rms() {
        let n = 64;
        let b = parse_generator("brushed:n=64,slope=0.25,seed=7")
            .unwrap()
            .build()
            .unwrap();
        // Slopes along x (wrapping) are the same on every row; along y they are zero.
        let mut sx: Vec<f64> = (0..n).map(|x| b.at(x + 1, 0) - b.at(x, 0)).collect();
        for y in 0..n {
            for x in 0..n {
                assert!((b.at(x + 1, y) - b.at(x, y) - sx[x as usize]).abs() < 1e-12);
                assert_eq!(b.at(x, y + 1), b.at(x, y));
            }
        }
        let rms = (sx.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        assert!((rms - 0.25).abs() < 1e-12, "RMS slope {rms}");
        // Sorted, they are the normal quantiles at (r + 1/2)/n up to one scale.
        sx.sort_by(f64::total_cmp);
        let scale = sx[n as usize - 1] / normal_quantile((n as f64 - 0.5) / n as f64);
        for (r, s) in sx.iter().enumerate() {
            let q = normal_quantile((r as f64 + 0.5) / n as f64);
            assert!(
                (s - scale * q).abs() < 1e-12,
                "slope rank {r}: {s} vs {}",
                scale * q
            );
        }
        // Reference values of the quantile function (to its 1.2e-9 relative accuracy).
        for (p, z) in [
            (0.5, 0.0),
            (0.975, 1.959963984540054),
            (0.001, -3.090232306167814),
        ] {
            assert!(
                (normal_quantile(p) - z).abs() <= 1e-8 * z.abs().max(1.0),
                "{p}"
            );
        }
        // slope_y adds an independent profile along y; both triangles of a cell share the
        // separable slopes, so the two axes' spreads are independent.
        let c = parse_generator("brushed:n=64,slope=0.2,slope_y=0.1,seed=7")
            .unwrap()
            .build()
            .unwrap();
        let sy: Vec<f64> = (0..n).map(|y| c.at(0, y + 1) - c.at(0, y)).collect();
        let rms_y = (sy.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        assert!((rms_y - 0.1).abs() < 1e-12, "RMS slope along y {rms_y}");
        for bad in [
            "brushed:n=64,kmax=33",
            "brushed:kmin=5,kmax=4",
            "brushed:slope=-1",
        ] {
            let e = parse_generator(bad).unwrap_err().to_string();
            assert!(
                e.contains("key 'k") || e.contains("key 'slope'"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn shape_params_leave_out_integers_seeds_amplitudes_and_zeros() {
        let keys = |spec: &str| -> Vec<&'static str> {
            parse_generator(spec)
                .unwrap()
                .shape_params()
                .into_iter()
                .map(|(k, _)| k)
                .collect()
        };
        assert_eq!(
            keys("bricks:length=30,height=13,mortar=2,depth=2"),
            ["length", "height", "mortar"]
        );
        assert_eq!(keys("bumps:count=5,radius=4,height=2,seed=3"), ["radius"]);
        assert_eq!(keys("fbm:cells=3"), ["persistence", "lacunarity"]);
        assert!(keys("brushed:slope=0.2").is_empty());
        assert_eq!(keys("brushed:slope=0.2,slope_y=0.1"), ["slope_y"]);
        assert!(keys("flat").is_empty());
    }

    #[test]
    fn bricks_have_one_sample_walls_and_weave_alternates() {
        let b = parse_generator("bricks:n=64,length=16,height=8,mortar=2,depth=3")
            .unwrap()
            .build()
            .unwrap();
        let vals: std::collections::BTreeSet<u64> =
            b.samples().iter().map(|v| v.to_bits()).collect();
        assert_eq!(vals.len(), 2, "only mortar and brick top");
        assert_eq!(b.at(0, 0), 0.0);
        assert_eq!(b.at(5, 5), 3.0);
        // Odd rows are offset by half a brick: the joint at x = 8 on row 1 (y in 8..16).
        assert_eq!(b.at(8, 12), 0.0);
        assert_eq!(b.at(8, 4), 3.0);
        let w = parse_generator("weave:n=64,period=16,height=1")
            .unwrap()
            .build()
            .unwrap();
        // Cell centres of threads (8, 8) and (24, 8): warp over, then weft over; both near the top.
        assert!(w.at(8, 8) > 0.9 && w.at(24, 8) > 0.9);
    }

    #[test]
    fn canonical_name_round_trips() {
        let g = parse_generator(" Bumps : radius=10 , seed=3, ").unwrap();
        assert_eq!(g.name(), "bumps:n=128,count=12,radius=10,height=4,seed=3");
        assert_eq!(parse_generator(&g.name()).unwrap(), g);
        let t = parse_generator("texture:file=/tmp/x.png,patch=2").unwrap();
        assert_eq!(
            t.name(),
            "texture:n=128,file=/tmp/x.png,patch=2,amplitude=4,cutoff=4,seed=0"
        );
        assert_eq!(parse_generator(&t.name()).unwrap(), t);
        let u = g.with_param("count", "3").unwrap();
        assert_eq!(u.get("count"), Some(3.0));
        assert_eq!(u.get("seed"), Some(3.0));
        assert!(g.with_param("count", "-3").is_err());
        for (name, help) in list() {
            let g = parse_generator(name).unwrap();
            for item in g.name().split_once(':').unwrap().1.split(',') {
                assert!(help.contains(item), "help of {name} lacks '{item}': {help}");
            }
        }
    }

    #[test]
    fn spec_errors_name_spec_and_key() {
        let cases: &[(&str, &[&str])] = &[
            ("blob:n=3", &["blob:n=3", "unknown", "vgroove", "weave"]),
            (
                "vgroove:size=3",
                &["vgroove:size=3", "'size'", "period, depth"],
            ),
            ("vgroove:period=abc", &["period", "not a number"]),
            ("vgroove:period=1", &["period", "at least 2"]),
            ("vgroove:period=200", &["period", "at most n"]),
            ("vgroove:depth=-1", &["depth", ">= 0"]),
            ("vgroove:depth=inf", &["depth", "finite"]),
            ("sine:amplitude=NaN", &["amplitude", "finite"]),
            ("flat:n=3", &["'n'", "4 to 4096"]),
            ("flat:n=5000", &["'n'"]),
            ("flat:n=64.5", &["'n'", "integer"]),
            ("bumps:count=2.5", &["count", "integer"]),
            ("bumps:seed=-1", &["seed"]),
            ("bumps:radius=0", &["radius", "> 0"]),
            ("ugroove:period=8,width=9", &["width", "period"]),
            ("bricks:length=8,height=8,mortar=8", &["mortar"]),
            ("vgroove:period", &["key=value"]),
            ("vgroove:period=4,period=5", &["twice"]),
            ("texture:tex=nope", &["tex", "cells"]),
            ("texture:tex=cells,file=a.png", &["not both"]),
            ("texture:n=16,file=", &["file", "no value"]),
            ("fbm:persistence=0", &["persistence"]),
        ];
        for (spec, needles) in cases {
            let e = parse_generator(spec).unwrap_err().to_string();
            assert!(e.contains(spec.trim()), "{spec}: {e}");
            for nd in *needles {
                assert!(e.contains(nd), "{spec}: '{e}' lacks '{nd}'");
            }
        }
        let e = parse_generator("texture:file=/nonexistent/tex.png")
            .unwrap()
            .build()
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/tex.png"), "{e}");
    }
}
