//! The look a solve aims at: a large-scale target BRDF (any material spec, anisotropic Ward,
//! a MERL file) with the Sec. 7 edits, or the `fbar` of a bi-scale combination (for validation),
//! and an optional target colour.

use crate::bvndf::CompactBvndf;
use crate::error::{Error, Result};
use crate::frame::{DirPair, Vec3};
use crate::prefilter::Prefiltered;
use crate::sampling::Samples;
use crate::target::{Target, TargetBase};
use std::sync::{Arc, Mutex};

/// One sample set drawn for a look ([`Look::memo`]): its key and the samples with the look's
/// values at them.
type SampleMemo = (Vec<u64>, Arc<(Samples, Vec<f64>)>);

/// A target look: `fbar(wi, wo)` and its average colour.
#[derive(Clone)]
pub struct Look {
    pub name: String,
    f: Arc<dyn Fn(Vec3, Vec3) -> f64 + Send + Sync>,
    /// Target average colour `lambda` (Eq. 13), if any.
    pub colour: Option<[f64; 3]>,
    /// Sample sets already drawn for this look (see [`Look::memo`]), shared by clones.
    memo: Arc<Mutex<Vec<SampleMemo>>>,
}

impl std::fmt::Debug for Look {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Look({})", self.name)
    }
}

/// Edits of Sec. 7 applied to a target spec.
#[derive(Debug, Clone, Copy)]
pub struct Edits {
    pub brightness: f64,
    pub contrast: f64,
    /// Angular blur (> 1) / sharpen (< 1) of the highlight along x and y; different values make it
    /// anisotropic ([`Target::with_angular`]).
    pub blur: [f64; 2],
}

impl Default for Edits {
    fn default() -> Self {
        Edits {
            brightness: 1.0,
            contrast: 1.0,
            blur: [1.0, 1.0],
        }
    }
}

impl Look {
    /// A target spec (`ward:ax=0.3,ay=0.08`, `blinn:n=60+lambert:albedo=0.2`, a MERL path) with
    /// edits; its colour is the material's average colour unless `colour` is given.
    pub fn from_spec(spec: &str, edits: Edits, colour: Option<[f64; 3]>) -> Result<Self> {
        let t = Target::parse(spec)?
            .with_brightness(edits.brightness)?
            .with_contrast(edits.contrast)?
            .with_angular(edits.blur[0], edits.blur[1])?;
        let own = match &t.base {
            TargetBase::Flat(m) => {
                Some(crate::library::items::average_colour(m).map(|c| c * edits.brightness))
            }
            TargetBase::AnisoWard(_) => None,
        };
        let t = Arc::new(t);
        Ok(Look {
            name: spec.to_string(),
            f: Arc::new(move |wi, wo| t.fbar(wi, wo)),
            colour: colour.or(own),
            memo: Arc::default(),
        })
    }

    /// A look given by a function (a bi-scale combination evaluated by some evaluator).
    pub fn from_fn(
        name: &str,
        f: impl Fn(Vec3, Vec3) -> f64 + Send + Sync + 'static,
        colour: Option<[f64; 3]>,
    ) -> Self {
        Look {
            name: name.to_string(),
            f: Arc::new(f),
            colour,
            memo: Arc::default(),
        }
    }

    /// The look of a bi-scale combination under the fast forward model: `geo`'s compact BVNDF
    /// with the prefiltered material `pre` (split or not, [`crate::fast::fbar_with_facets`]),
    /// times `scale` (a brightness edit).
    pub fn from_combination(
        name: &str,
        geo: Arc<CompactBvndf>,
        pre: Arc<Prefiltered>,
        scale: f64,
        colour: Option<[f64; 3]>,
    ) -> Self {
        // The facets' rays, prepared once, only for a material with sharp lobes.
        let rays = pre
            .sharp()
            .map(|_| crate::facetrays::FacetRays::owned(geo.relief.clone()));
        Look::from_fn(
            name,
            move |wi: Vec3, wo: Vec3| {
                let mut scratch = Vec::with_capacity(geo.clusters);
                let p = DirPair { wi, wo };
                scale
                    * crate::fast::fbar_one_with_facets(&geo, &pre, rays.as_ref(), &p, &mut scratch)
            },
            colour,
        )
    }

    /// Refuse a black look: `fbar` zero (or not finite) at every one of the 490 default pairs
    /// (`brightness = 0`, `lambert:albedo=0`, `ks=0`, a measured file of zeros). Its relative
    /// error has no scale, so no answer could be ranked; better said at once than after a search.
    pub fn check_not_black(&self) -> Result<()> {
        let lit = crate::pairs::default_pairs(70).iter().any(|p| {
            let d = p.dirs();
            let v = self.fbar(d.wi, d.wo);
            v.is_finite() && v > 0.0
        });
        if lit {
            Ok(())
        } else {
            Err(Error::new(
                self.name.clone(),
                "the look is black (fbar is 0 at every one of the 490 default direction pairs): \
                 a black target has no relative error to match; expected a look that reflects \
                 some light",
            ))
        }
    }

    /// The sample set stored under `key` (drawn by `make` the first time). Drawing samples
    /// evaluates the look a few tens of thousands of times (the gradient of importance
    /// sampling); the general solver asks for the same set at every iteration.
    pub fn memo(
        &self,
        key: Vec<u64>,
        make: impl FnOnce() -> (Samples, Vec<f64>),
    ) -> Arc<(Samples, Vec<f64>)> {
        if let Some(hit) = self
            .memo
            .lock()
            .ok()
            .and_then(|m| m.iter().find(|e| e.0 == key).map(|e| e.1.clone()))
        {
            return hit;
        }
        let v = Arc::new(make());
        if let Ok(mut m) = self.memo.lock() {
            m.push((key, v.clone()));
        }
        v
    }

    /// `fbar(wi, wo)`.
    pub fn fbar(&self, wi: Vec3, wo: Vec3) -> f64 {
        (self.f)(wi, wo)
    }

    /// The look as a plain function (for sampling).
    pub fn as_fn(&self) -> impl Fn(Vec3, Vec3) -> f64 + Sync + '_ {
        move |wi, wo| (self.f)(wi, wo)
    }

    /// `fbar` at pairs.
    pub fn values(&self, pairs: &[DirPair]) -> Vec<f64> {
        pairs.iter().map(|p| self.fbar(p.wi, p.wo)).collect()
    }
}

/// Parse a blur factor `S` or `SX,SY`.
pub fn parse_blur(s: &str) -> Result<[f64; 2]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::new(
                "--blur",
                format!("'{s}': expected S or SX,SY, e.g. 2 or 3,0.8"),
            )
        })?;
    match v.as_slice() {
        [a] => Ok([*a, *a]),
        [a, b] => Ok([*a, *b]),
        _ => Err(Error::new(
            "--blur",
            format!("'{s}': expected one or two factors"),
        )),
    }
}

/// Parse `r,g,b` (each ≥ 0).
pub fn parse_colour(s: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .split([',', ':'])
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::new(
                "--colour",
                format!("'{s}': expected r,g,b, e.g. 0.8,0.5,0.2"),
            )
        })?;
    match v[..] {
        [r, g, b] => check_colour(&format!("--colour '{s}'"), [r, g, b]),
        _ => Err(Error::new(
            "--colour",
            format!("'{s}': {}", COLOUR_EXPECTED),
        )),
    }
}

const COLOUR_EXPECTED: &str = "expected three numbers in [0, 1e6], not all 0";

/// A target colour as `solve --colour` and a scene's `colour` take it: three channels in
/// `[0, 1e6]`, not all 0 (a black target has no scale for the relative error). `what` names
/// where it came from in the error.
pub fn check_colour(what: &str, c: [f64; 3]) -> Result<[f64; 3]> {
    if c.iter().any(|x| !(x.is_finite() && *x >= 0.0 && *x <= 1e6)) || c.iter().all(|x| *x == 0.0) {
        return Err(Error::new(what, format!("{c:?}: {COLOUR_EXPECTED}")));
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn black_looks_are_refused_naming_the_target() {
        for spec in ["lambert:albedo=0", "ggx:alpha=0.2,ks=0"] {
            let look = Look::from_spec(spec, Edits::default(), None).unwrap();
            let e = look.check_not_black().unwrap_err().to_string();
            assert!(e.contains(spec) && e.contains("black"), "{e}");
        }
        let look = Look::from_spec("ward:ax=0.3,ay=0.08", Edits::default(), None).unwrap();
        assert!(look.check_not_black().is_ok());
    }
}
