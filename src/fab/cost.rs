//! Cost of one tile: material, machine time, stock, and the profile's weighted total.
//!
//! Model (tile `X × Y` mm, made surface of relief `R`, base `B`, all from the catalogue entries):
//! - **Material** = `cost_per_cm2` × tile area (surface finish) + `cost_per_cm3` × stock volume.
//!   The stock is the block `X · Y · (B + R)` for a mill, the printed volume
//!   `X · Y · B + ∫ (z − z_min) dA` for a printer.
//! - **Mill time** = roughing + finishing. Roughing removes the volume between the block top and
//!   the made surface at a material removal rate of `(d/2) · (d/2) · feed` mm³/min (stepdown
//!   and stepover of half the tool diameter `d`). Finishing is a zig-zag raster of passes along x
//!   spaced by `stepover_mm` across y (`ceil(Y / stepover) + 1` passes): each pass follows the
//!   made surface, so its length is `X` times the mean 3-D arc length per unit x of the surface's
//!   rows, plus one stepover link per pass, all at `feed_mm_per_min`; one plunge of `B + R`
//!   at `plunge_mm_per_min` starts the job. Rapid moves and tool changes are not counted.
//! - **SLA time** = part height `(B + R)` / `print_speed_mm_per_h` (a vat printer exposes a
//!   whole layer at once). **FDM time** = extruded path length (printed volume / (nozzle ·
//!   layer)) / `speed_mm_per_s`.
//! - **Total** = `weight_material` × material cost + `weight_time_per_h` × hours, in the
//!   profile's weighted cost units.

use super::catalogue::Machine;
use super::morph::Grid;
use super::profile::Profile;

/// Every cost term of one tile, with units in the names.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CostReport {
    pub currency: String,
    pub tile_x_mm: f64,
    pub tile_y_mm: f64,
    pub area_cm2: f64,
    /// Stock block (mill) or printed volume (printer).
    pub stock_cm3: f64,
    pub finish_cost: f64,
    pub stock_cost: f64,
    /// finish + stock, in `currency`.
    pub material_cost: f64,
    pub roughing_h: f64,
    pub finishing_h: f64,
    /// Total machine (or printer) time.
    pub time_h: f64,
    /// Length of the finishing raster (mills) or of the extruded path (FDM), mm.
    pub path_mm: Option<f64>,
    pub weighted_material: f64,
    pub weighted_time: f64,
    /// weighted_material + weighted_time.
    pub total: f64,
}

/// Mean 3-D arc length per unit x of the rows of a periodic surface (>= 1).
fn row_length_factor(g: &Grid) -> f64 {
    let mut sum = 0.0;
    for y in 0..g.h {
        let row = &g.z[y * g.w..(y + 1) * g.w];
        for x in 0..g.w {
            let dz = row[(x + 1) % g.w] - row[x];
            sum += (g.cell_mm * g.cell_mm + dz * dz).sqrt();
        }
    }
    let len = (g.w * g.h) as f64 * g.cell_mm;
    if len > 0.0 {
        sum / len
    } else {
        1.0
    }
}

/// Cost of a `tile_x_mm × tile_y_mm` tile of the made surface `made` (heights in mm, one period).
pub fn tile_cost(profile: &Profile, made: &Grid, tile_x_mm: f64, tile_y_mm: f64) -> CostReport {
    let (lo, hi) = made.min_max();
    let relief = (hi - lo).max(0.0);
    let mean = made.z.iter().sum::<f64>() / made.z.len().max(1) as f64;
    let area = tile_x_mm * tile_y_mm;
    let base = profile.base_thickness_mm;
    let height = base + relief;
    let printed_mm3 = area * (base + (mean - lo).max(0.0));
    let (stock_mm3, roughing_h, finishing_h, path_mm) = match (&profile.machine, &profile.tool) {
        (Machine::Mill(m), Some(t)) => {
            let removed = area * (hi - mean).max(0.0);
            let mrr = 0.25 * t.diameter_mm * t.diameter_mm * m.feed_mm_per_min;
            let rough = removed / mrr / 60.0;
            let s = profile.stepover_mm.unwrap_or(0.5 * t.diameter_mm);
            let passes = (tile_y_mm / s).ceil() + 1.0;
            let path = passes * (tile_x_mm * row_length_factor(made) + s);
            let finish = path / m.feed_mm_per_min / 60.0 + height / m.plunge_mm_per_min / 60.0;
            (area * height, rough, finish, Some(path))
        }
        (Machine::Sla(s), _) => (printed_mm3, 0.0, height / s.print_speed_mm_per_h, None),
        (Machine::Fdm(f), _) => {
            let path = printed_mm3 / (f.nozzle_mm * f.layer_mm);
            (
                printed_mm3,
                0.0,
                path / f.speed_mm_per_s / 3600.0,
                Some(path),
            )
        }
        (Machine::Mill(_), None) => (area * height, 0.0, 0.0, None),
    };
    let area_cm2 = area / 100.0;
    let stock_cm3 = stock_mm3 / 1000.0;
    let finish_cost = profile.material.cost_per_cm2 * area_cm2;
    let stock_cost = profile.material.cost_per_cm3 * stock_cm3;
    let material_cost = finish_cost + stock_cost;
    let time_h = roughing_h + finishing_h;
    let weighted_material = profile.weight_material * material_cost;
    let weighted_time = profile.weight_time_per_h * time_h;
    CostReport {
        currency: profile.material.currency.clone(),
        tile_x_mm,
        tile_y_mm,
        area_cm2,
        stock_cm3,
        finish_cost,
        stock_cost,
        material_cost,
        roughing_h,
        finishing_h,
        time_h,
        path_mm,
        weighted_material,
        weighted_time,
        total: weighted_material + weighted_time,
    }
}
