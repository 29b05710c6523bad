//! The constraint catalogues in `constraints/`: cutting tools (`tools.toml`), machines and
//! printers (`machines.toml`) and stock materials with their costs (`materials.toml`). Each file
//! is a set of named tables (`[ball-1mm]`, `[mill-3axis]`, ...) that profiles refer to by name.
//! Every size is in millimetres and every key says its unit (`diameter_mm`, `feed_mm_per_min`).

use crate::error::{Error, Result};
use crate::tomlfile::{non_negative, parse, positive, read_text, required};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The cutter's end shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ToolKind {
    /// Ball-nose: a cylinder ending in a hemisphere of radius `diameter_mm / 2`.
    Ball,
    /// Flat-end: a cylinder with a flat disc of diameter `diameter_mm` at its tip.
    Flat,
}

/// One cutting tool of `tools.toml`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Tool {
    pub name: String,
    pub kind: ToolKind,
    pub diameter_mm: f64,
    /// Cutting length: the deepest relief the tool reaches without the holder touching the part.
    pub flute_length_mm: f64,
}

/// A 3-axis milling machine.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Mill {
    pub travel_x_mm: f64,
    pub travel_y_mm: f64,
    pub travel_z_mm: f64,
    pub resolution_mm: f64,
    pub feed_mm_per_min: f64,
    pub plunge_mm_per_min: f64,
}

/// A resin (SLA) printer.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Sla {
    pub build_x_mm: f64,
    pub build_y_mm: f64,
    pub build_z_mm: f64,
    pub xy_resolution_mm: f64,
    pub z_resolution_mm: f64,
    /// Vertical build speed (independent of the part's area, as for any vat printer).
    pub print_speed_mm_per_h: f64,
}

/// A filament (FDM) printer.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Fdm {
    pub build_x_mm: f64,
    pub build_y_mm: f64,
    pub build_z_mm: f64,
    pub nozzle_mm: f64,
    pub layer_mm: f64,
    /// Extrusion path speed.
    pub speed_mm_per_s: f64,
}

/// What a machine is, with its own keys.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Machine {
    Mill(Mill),
    Sla(Sla),
    Fdm(Fdm),
}

impl Machine {
    /// `"mill"`, `"sla"` or `"fdm"`, as written in `machines.toml`.
    pub fn kind(&self) -> &'static str {
        match self {
            Machine::Mill(_) => "mill",
            Machine::Sla(_) => "sla",
            Machine::Fdm(_) => "fdm",
        }
    }
    /// The largest part footprint and height (x, y, z in mm).
    pub fn envelope_mm(&self) -> (f64, f64, f64) {
        match self {
            Machine::Mill(m) => (m.travel_x_mm, m.travel_y_mm, m.travel_z_mm),
            Machine::Sla(m) => (m.build_x_mm, m.build_y_mm, m.build_z_mm),
            Machine::Fdm(m) => (m.build_x_mm, m.build_y_mm, m.build_z_mm),
        }
    }
}

/// A stock material of `materials.toml`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StockMaterial {
    pub name: String,
    /// Machine kinds that can work it (`"mill"`, `"sla"`, `"fdm"`).
    pub processes: Vec<String>,
    /// Surface finish (coating, polishing, anodising) per cm² of tile.
    pub cost_per_cm2: f64,
    /// Stock (block, resin, filament) per cm³.
    pub cost_per_cm3: f64,
    pub currency: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ToolRaw {
    description: Option<String>,
    kind: Option<String>,
    diameter_mm: Option<f64>,
    flute_length_mm: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MachineRaw {
    description: Option<String>,
    kind: Option<String>,
    travel_x_mm: Option<f64>,
    travel_y_mm: Option<f64>,
    travel_z_mm: Option<f64>,
    resolution_mm: Option<f64>,
    feed_mm_per_min: Option<f64>,
    plunge_mm_per_min: Option<f64>,
    build_x_mm: Option<f64>,
    build_y_mm: Option<f64>,
    build_z_mm: Option<f64>,
    xy_resolution_mm: Option<f64>,
    z_resolution_mm: Option<f64>,
    print_speed_mm_per_h: Option<f64>,
    nozzle_mm: Option<f64>,
    layer_mm: Option<f64>,
    speed_mm_per_s: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialRaw {
    description: Option<String>,
    processes: Option<Vec<String>>,
    cost_per_cm2: Option<f64>,
    cost_per_cm3: Option<f64>,
    currency: Option<String>,
}

/// The three catalogues, by name.
#[derive(Debug, Clone)]
pub struct Catalogue {
    pub dir: PathBuf,
    pub tools: BTreeMap<String, Tool>,
    pub machines: BTreeMap<String, Machine>,
    pub materials: BTreeMap<String, StockMaterial>,
}

fn names<T>(m: &BTreeMap<String, T>) -> String {
    m.keys()
        .map(|k| format!("\"{k}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Look `name` up in one catalogue; the error lists the known names.
pub fn lookup<'a, T>(
    m: &'a BTreeMap<String, T>,
    what: &str,
    name: &str,
    catalogue_file: &Path,
) -> Result<&'a T> {
    m.get(name).ok_or_else(|| {
        Error::new(
            catalogue_file.display().to_string(),
            if m.is_empty() {
                format!("no {what} named \"{name}\": this catalogue defines no {what}")
            } else {
                format!(
                    "no {what} named \"{name}\"; the known {what}s are {}",
                    names(m)
                )
            },
        )
    })
}

fn load_tools(path: &Path) -> Result<BTreeMap<String, Tool>> {
    let raw: BTreeMap<String, ToolRaw> = parse(path, &read_text(path)?)?;
    let mut out = BTreeMap::new();
    for (name, r) in raw {
        let s = format!("[{name}] ");
        let _ = r.description;
        let kind = match required(path, &s, "kind", r.kind, "\"ball\" or \"flat\"")?.as_str() {
            "ball" => ToolKind::Ball,
            "flat" => ToolKind::Flat,
            other => {
                return Err(Error::new(
                    path.display().to_string(),
                    format!("{s}key `kind` must be \"ball\" or \"flat\", got \"{other}\""),
                ))
            }
        };
        let d = required(path, &s, "diameter_mm", r.diameter_mm, "a number of mm")?;
        let f = required(
            path,
            &s,
            "flute_length_mm",
            r.flute_length_mm,
            "a number of mm",
        )?;
        out.insert(
            name.clone(),
            Tool {
                name,
                kind,
                diameter_mm: positive(path, &s, "diameter_mm", d, "mm")?,
                flute_length_mm: positive(path, &s, "flute_length_mm", f, "mm")?,
            },
        );
    }
    Ok(out)
}

fn load_machines(path: &Path) -> Result<BTreeMap<String, Machine>> {
    let raw: BTreeMap<String, MachineRaw> = parse(path, &read_text(path)?)?;
    let mut out = BTreeMap::new();
    for (name, r) in raw {
        let s = format!("[{name}] ");
        let _ = &r.description;
        let kind = required(
            path,
            &s,
            "kind",
            r.kind.clone(),
            "\"mill\", \"sla\" or \"fdm\"",
        )?;
        let all: [(&str, Option<f64>); 15] = [
            ("travel_x_mm", r.travel_x_mm),
            ("travel_y_mm", r.travel_y_mm),
            ("travel_z_mm", r.travel_z_mm),
            ("resolution_mm", r.resolution_mm),
            ("feed_mm_per_min", r.feed_mm_per_min),
            ("plunge_mm_per_min", r.plunge_mm_per_min),
            ("build_x_mm", r.build_x_mm),
            ("build_y_mm", r.build_y_mm),
            ("build_z_mm", r.build_z_mm),
            ("xy_resolution_mm", r.xy_resolution_mm),
            ("z_resolution_mm", r.z_resolution_mm),
            ("print_speed_mm_per_h", r.print_speed_mm_per_h),
            ("nozzle_mm", r.nozzle_mm),
            ("layer_mm", r.layer_mm),
            ("speed_mm_per_s", r.speed_mm_per_s),
        ];
        let wanted: &[&str] = match kind.as_str() {
            "mill" => &MILL_KEYS,
            "sla" => &SLA_KEYS,
            "fdm" => &FDM_KEYS,
            other => {
                return Err(Error::new(
                    path.display().to_string(),
                    format!("{s}key `kind` must be \"mill\", \"sla\" or \"fdm\", got \"{other}\""),
                ))
            }
        };
        let mut v = Vec::with_capacity(6);
        for (k, val) in all.iter() {
            match (wanted.contains(k), val) {
                (true, Some(x)) => v.push(positive(path, &s, k, *x, unit_of(k))?),
                (true, None) => {
                    return Err(Error::new(
                        path.display().to_string(),
                        format!(
                            "{s}missing key `{k}` (a {kind} needs {})",
                            wanted.join(", ")
                        ),
                    ))
                }
                (false, Some(_)) => {
                    return Err(Error::new(
                        path.display().to_string(),
                        format!(
                            "{s}key `{k}` does not apply to kind \"{kind}\" (its keys are {})",
                            wanted.join(", ")
                        ),
                    ))
                }
                (false, None) => {}
            }
        }
        let m = match kind.as_str() {
            "mill" => Machine::Mill(Mill {
                travel_x_mm: v[0],
                travel_y_mm: v[1],
                travel_z_mm: v[2],
                resolution_mm: v[3],
                feed_mm_per_min: v[4],
                plunge_mm_per_min: v[5],
            }),
            "sla" => Machine::Sla(Sla {
                build_x_mm: v[0],
                build_y_mm: v[1],
                build_z_mm: v[2],
                xy_resolution_mm: v[3],
                z_resolution_mm: v[4],
                print_speed_mm_per_h: v[5],
            }),
            _ => Machine::Fdm(Fdm {
                build_x_mm: v[0],
                build_y_mm: v[1],
                build_z_mm: v[2],
                nozzle_mm: v[3],
                layer_mm: v[4],
                speed_mm_per_s: v[5],
            }),
        };
        out.insert(name, m);
    }
    Ok(out)
}

const MILL_KEYS: [&str; 6] = [
    "travel_x_mm",
    "travel_y_mm",
    "travel_z_mm",
    "resolution_mm",
    "feed_mm_per_min",
    "plunge_mm_per_min",
];
const SLA_KEYS: [&str; 6] = [
    "build_x_mm",
    "build_y_mm",
    "build_z_mm",
    "xy_resolution_mm",
    "z_resolution_mm",
    "print_speed_mm_per_h",
];
const FDM_KEYS: [&str; 6] = [
    "build_x_mm",
    "build_y_mm",
    "build_z_mm",
    "nozzle_mm",
    "layer_mm",
    "speed_mm_per_s",
];

fn unit_of(key: &str) -> &'static str {
    if key.ends_with("_per_min") {
        "mm per minute"
    } else if key.ends_with("_per_h") {
        "mm per hour"
    } else if key.ends_with("_per_s") {
        "mm per second"
    } else {
        "mm"
    }
}

fn load_materials(path: &Path) -> Result<BTreeMap<String, StockMaterial>> {
    let raw: BTreeMap<String, MaterialRaw> = parse(path, &read_text(path)?)?;
    let mut out = BTreeMap::new();
    for (name, r) in raw {
        let s = format!("[{name}] ");
        let _ = r.description;
        let processes = required(
            path,
            &s,
            "processes",
            r.processes,
            "a list such as [\"mill\"]",
        )?;
        if processes.is_empty() {
            return Err(Error::new(
                path.display().to_string(),
                format!("{s}key `processes`: empty; expected the machine kinds that work this material, e.g. [\"mill\"]"),
            ));
        }
        if let Some(p) = processes
            .iter()
            .find(|p| !["mill", "sla", "fdm"].contains(&p.as_str()))
        {
            return Err(Error::new(
                path.display().to_string(),
                format!("{s}key `processes`: \"{p}\" is not a machine kind (expected \"mill\", \"sla\" or \"fdm\")"),
            ));
        }
        let c2 = required(
            path,
            &s,
            "cost_per_cm2",
            r.cost_per_cm2,
            "a cost per cm² >= 0",
        )?;
        let c3 = required(
            path,
            &s,
            "cost_per_cm3",
            r.cost_per_cm3,
            "a cost per cm³ >= 0",
        )?;
        out.insert(
            name.clone(),
            StockMaterial {
                name,
                processes,
                cost_per_cm2: non_negative(path, &s, "cost_per_cm2", c2, "currency per cm²")?,
                cost_per_cm3: non_negative(path, &s, "cost_per_cm3", c3, "currency per cm³")?,
                currency: required(
                    path,
                    &s,
                    "currency",
                    r.currency,
                    "a currency code such as \"EUR\"",
                )?,
            },
        );
    }
    Ok(out)
}

impl Catalogue {
    /// Load `tools.toml`, `machines.toml` and `materials.toml` from `dir`.
    pub fn load(dir: &Path) -> Result<Catalogue> {
        Ok(Catalogue {
            dir: dir.to_path_buf(),
            tools: load_tools(&dir.join("tools.toml"))?,
            machines: load_machines(&dir.join("machines.toml"))?,
            materials: load_materials(&dir.join("materials.toml"))?,
        })
    }
}
