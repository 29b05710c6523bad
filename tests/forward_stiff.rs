//! Stiff and extreme input (acceptance check 5): no NaN or inf anywhere, every value >= 0.
//! vMF lobes with kappa 1e-8 .. 1e6, Blinn exponents up to 1e5 (and the grammar's 1e7), GGX alpha
//! down to 1e-3, directions at 89.9°, and a flat and two extremely tall geometries through both
//! evaluators.

use biscale::bvndf::{BvndfConfig, CompactBvndf};
use biscale::exact::ExactEvaluator;
use biscale::fast;
use biscale::frame::{dir_from_deg, DirPair, Vec3};
use biscale::generators::parse_generator;
use biscale::heightfield::Heightfield;
use biscale::material::parse_material;
use biscale::prefilter::{PrefilterConfig, Prefiltered};
use biscale::vmf::Vmf;

fn ok(v: f64) -> bool {
    v.is_finite() && v >= 0.0
}

#[test]
fn vmf_eval_and_sample_are_finite_for_every_kappa() {
    let kappas = [
        0.0, 1e-8, 1e-6, 1e-4, 0.1, 1.0, 10.0, 100.0, 709.0, 711.0, 1e3, 1e4, 1e5, 1e6,
    ];
    let mus = [
        Vec3::Z,
        dir_from_deg(45.0, 30.0),
        dir_from_deg(89.9, 200.0),
        Vec3::new(0.0, 0.0, -1.0),
    ];
    let us = [
        0.0,
        1e-12,
        0.25,
        0.5,
        0.999,
        1.0 - 1e-12,
        1.0 - f64::EPSILON,
    ];
    for &k in &kappas {
        for &mu in &mus {
            let l = Vmf::new(k, mu);
            // density at the mean, near it, sideways and antipodal
            for n in [
                mu,
                (mu + Vec3::new(1e-4, 0.0, 0.0)).normalized(),
                Vec3::new(mu.y, -mu.x, 0.0).normalized(),
                -mu,
            ] {
                let n = if n.norm() > 0.0 {
                    n
                } else {
                    Vec3::new(1.0, 0.0, 0.0)
                };
                let v = l.eval(n);
                assert!(ok(v), "vMF kappa {k} mu {mu:?} eval({n:?}) = {v}");
            }
            let peak = l.eval(mu);
            assert!(peak > 0.0, "kappa {k}: density at the mean is {peak}");
            for &u in &us {
                for &v in &[0.0, 0.3, 0.999] {
                    let c = Vmf::sample_cos(k, u);
                    assert!(
                        c.is_finite() && (-1.0..=1.0).contains(&c),
                        "kappa {k} u {u}: cos {c}"
                    );
                    let d = l.sample(u, v);
                    assert!(
                        d.x.is_finite() && d.y.is_finite() && d.z.is_finite(),
                        "kappa {k} mu {mu:?} sample({u}, {v}) = {d:?}"
                    );
                    assert!((d.norm() - 1.0).abs() < 1e-9, "not unit: {d:?}");
                }
            }
        }
    }
}

fn stiff_materials() -> Vec<&'static str> {
    vec![
        "blinn:n=1e5",
        "blinn:n=1e7",
        "ggx:alpha=0.001",
        "beckmann:alpha=0.001",
        "ct:m=0.001",
        "ward:alpha=0.001",
        "ggx:alpha=0.001+lambert:albedo=1",
        "ggx:alpha=10",
    ]
}

fn grazing_pairs() -> Vec<DirPair> {
    let mut v = Vec::new();
    let angles = [
        (0.0, 0.0),
        (45.0, 30.0),
        (89.9, 0.0),
        (89.9, 180.0),
        (89.9, 90.0),
    ];
    for &(ti, pi) in &angles {
        for &(to, po) in &angles {
            v.push(DirPair {
                wi: dir_from_deg(ti, pi),
                wo: dir_from_deg(to, po),
            });
        }
    }
    // exact mirror configurations (peak of narrow lobes) at grazing
    v.push(DirPair {
        wi: dir_from_deg(89.9, 0.0),
        wo: dir_from_deg(89.9, 180.0),
    });
    v.push(DirPair {
        wi: dir_from_deg(30.0, 0.0),
        wo: dir_from_deg(30.0, 180.0),
    });
    v
}

#[test]
fn stiff_materials_are_finite_at_any_normal() {
    let normals = [
        Vec3::Z,
        dir_from_deg(1e-6, 0.0),
        dir_from_deg(30.0, 90.0),
        dir_from_deg(89.9, 180.0),
    ];
    for spec in stiff_materials() {
        let m = parse_material(spec).unwrap();
        for p in grazing_pairs() {
            for n in normals {
                let v = m.eval(n, p.wi, p.wo);
                assert!(ok(v), "{spec}: f_r({n:?}, {:?}, {:?}) = {v}", p.wi, p.wo);
            }
        }
    }
}

fn geometries() -> Vec<Heightfield> {
    [
        "flat:n=16",
        "fbm:n=32,amplitude=500",
        "bumps:n=32,height=1000",
    ]
    .iter()
    .map(|s| parse_generator(s).unwrap().build().unwrap())
    .collect()
}

#[test]
fn extreme_geometry_and_materials_through_the_exact_evaluator() {
    let pairs = grazing_pairs();
    for hf in geometries() {
        let ev = ExactEvaluator::new(&hf, 2);
        for spec in stiff_materials() {
            let m = parse_material(spec).unwrap();
            let v = ev.fbar(&m, &pairs);
            for (p, x) in pairs.iter().zip(&v) {
                assert!(ok(*x), "exact {} {spec} at {p:?}: {x}", hf.name);
            }
        }
        for p in &pairs {
            let a = ev.visible_projected_area(p.wo);
            assert!(ok(a), "a_v of {} at {:?}: {a}", hf.name, p.wo);
        }
    }
}

#[test]
fn extreme_geometry_and_materials_through_the_fast_evaluator() {
    let pairs = grazing_pairs();
    // A coarse table: this test is about finiteness at every kappa node (all 19 are kept), not
    // about accuracy, and the default table costs ~2 s per narrow material.
    let cfg = PrefilterConfig {
        n_half: 8,
        n_theta_mu: 12,
        n_phi_mu: 5,
        samples: 16,
    };
    let pres: Vec<(&str, Prefiltered)> = stiff_materials()
        .into_iter()
        .map(|s| {
            let p = Prefiltered::build(&parse_material(s).unwrap(), &cfg);
            assert!(
                p.table().iter().all(|v| v.is_finite() && *v >= 0.0),
                "prefiltered table of {s} has a non-finite or negative entry"
            );
            (s, p)
        })
        .collect();
    // The `forward` command's build too (finer grid, seen rays; seen rays need more cells than
    // marched rays, hence the 64² surface).
    let tall = parse_generator("fbm:n=64,amplitude=800")
        .unwrap()
        .build()
        .unwrap();
    let builds = geometries()
        .into_iter()
        .map(|hf| (hf, BvndfConfig::default()))
        .chain([(tall, BvndfConfig::forward())]);
    for (hf, bcfg) in builds {
        let geo = CompactBvndf::build(&hf, &bcfg);
        assert!(
            geo.table.iter().all(|v| v.is_finite()),
            "compact BVNDF of {} has a non-finite entry",
            hf.name
        );
        let mut lobes = Vec::new();
        for p in &pairs {
            geo.lobes(p.wi, p.wo, true, &mut lobes);
            for (w, l) in &lobes {
                assert!(
                    ok(*w)
                        && l.kappa.is_finite()
                        && l.kappa >= 0.0
                        && (l.mu.norm() - 1.0).abs() < 1e-6,
                    "lobe of {} at {p:?}: weight {w}, {l:?}",
                    hf.name
                );
            }
        }
        for (spec, pre) in &pres {
            let v = fast::fbar(&geo, pre, &pairs);
            for (p, x) in pairs.iter().zip(&v) {
                assert!(ok(*x), "fast {} {spec} at {p:?}: {x}", hf.name);
            }
            // As `forward` runs it: lobes narrower than FACET_WIDTH summed over facets.
            let split =
                Prefiltered::build_split(&parse_material(spec).unwrap(), &cfg, fast::FACET_WIDTH);
            let v = fast::fbar_with_facets(&geo, &split, &pairs);
            for (p, x) in pairs.iter().zip(&v) {
                assert!(ok(*x), "fast (facets) {} {spec} at {p:?}: {x}", hf.name);
            }
        }
    }
}

/// The tallest surfaces accepted (heights up to `MAX_HEIGHT` cells) go through both evaluators
/// and agree (they used to march for ever: a hit point `zmax / m` cells from its ray's start
/// lost the nudge that moves a walk past a skipped block, and a slope tolerance proportional to
/// the relief kept shadow marches from deciding); taller ones are refused with the limit named.
#[test]
fn surfaces_up_to_the_height_limit_finish_and_beyond_it_are_refused() {
    let pairs: Vec<DirPair> = [
        (30.0, 0.0, 40.0, 0.0),
        (60.0, 90.0, 89.9, 270.0),
        (89.9, 0.0, 89.9, 0.0),
    ]
    .iter()
    .map(|&(ti, pi, to, po)| DirPair {
        wi: dir_from_deg(ti, pi),
        wo: dir_from_deg(to, po),
    })
    .collect();
    let m = parse_material("ggx:alpha=0.2+lambert:albedo=0.5").unwrap();
    let pf = Prefiltered::build(&m, &PrefilterConfig::default());
    let mut first = Vec::new();
    for amp in ["1e3", "1e9"] {
        let hf = parse_generator(&format!("sine:n=32,period=16,amplitude={amp}"))
            .unwrap()
            .build()
            .unwrap();
        let exact = ExactEvaluator::new(&hf, 2).fbar(&m, &pairs);
        let fast = fast::fbar(
            &CompactBvndf::build(&hf, &BvndfConfig::default()),
            &pf,
            &pairs,
        );
        for (e, f) in exact.iter().zip(&fast) {
            assert!(ok(*e) && ok(*f), "amplitude {amp}: exact {e}, fast {f}");
        }
        // Walls of slope 400 or 4e8 look alike: the same fbar to 2 % at 40° (the fast method's
        // own error there is under 1 %).
        assert!(
            (fast[0] - exact[0]).abs() < 0.02 * exact[0],
            "{amp}: {fast:?} vs {exact:?}"
        );
        first.push(exact[0]);
    }
    assert!((first[1] - first[0]).abs() < 0.02 * first[0], "{first:?}");
    let e = parse_generator("sine:n=32,period=16,amplitude=2e9")
        .unwrap()
        .build()
        .unwrap_err()
        .to_string();
    assert!(e.contains("1e9") && e.contains("row"), "{e}");
}
