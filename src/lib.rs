//! biscale: inverse bi-scale material design for fabrication (Wu, Dorsey, Rushmeier).
//!
//! The library holds all behaviour; `src/main.rs` is a thin command line over it. See
//! `docs/architecture.md` for the modules and how data flows between them.

// `!(x > 0.0)` and the like are deliberate: they are true for NaN, which every input check and
// range guard must reject; `partial_cmp` would hide that.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// The module docs explain the code by naming private helpers; read them with
// `cargo doc --document-private-items`, where those links resolve.
#![allow(rustdoc::private_intra_doc_links)]

pub mod cpu;
pub mod error;
pub mod fastmath;
pub mod frame;
pub mod prefetch;
pub mod rng;

// Small-scale materials and large-scale targets.
pub mod material;
pub mod target;

// Small-scale geometry.
pub mod generators;
pub mod heightfield;
pub mod heightmap_io;
pub mod npy;
pub mod texture;

// Visibility, BVNDF and the two evaluators of fbar.
pub mod bvndf;
pub mod dirgrid;
pub mod exact;
pub mod facetindex;
pub mod facetrays;
pub mod fast;
pub mod gamma;
pub mod jointvis;
pub mod lightlobes;
pub mod lobecodec;
pub mod lobepack;
pub mod prefilter;
pub mod seen;
pub mod sublobes;
pub mod visibility;
pub mod vmf;

// Libraries: compression and representatives.
pub mod library;
pub mod lowrank;
pub mod plot;
pub mod sampling;
pub mod solve;
pub mod store;
pub mod tomlfile;
pub mod uf8;
pub mod validate;

// Files and commands.
pub mod atomic_write;
pub mod design;
pub mod interrupt;
pub mod render;
// Fabrication: constraint profiles, millability, cost, export.
pub mod bench;
pub mod fab;
pub mod forward;
pub mod pairs;

#[cfg(test)]
pub(crate) mod testdir;

pub use error::{Error, Result};
