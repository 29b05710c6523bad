//! The compact BVNDF at the library's fixed lights: each library geometry's own accurate data,
//! with which the solvers re-rank candidates without rebuilding anything.
//!
//! The binned column of [`crate::gamma`] is linear in `gamma` (what the compressed search needs)
//! but its normal grid cannot resolve narrow material lobes. The full compact BVNDF of
//! [`crate::bvndf`] can, but tabulates every pair of 160 grid directions and takes 0.1–0.8 s to
//! build. Every solver sample is lit from one of the library's 7 lights ([`crate::sampling`]), so
//! the light side need not be tabulated: per light `l`, per view node `b` of the library's
//! [`crate::dirgrid::DirGrid`] and per normal cluster `c`, this table stores the moments of
//! [`crate::bvndf`] of the area seen from `w_b` and lit from `w_l`, `G1 = Σ A n` and
//! `G2 = Σ A n nᵀ` (9 numbers), plus the moments `G1` of the area seen from `w_b` alone (the
//! visible projected area `a_v`). They are accumulated in the same pass of view rays as the
//! binned column ([`GammaLayout::trace`]), so a library build gets them almost for free, and
//! lobes are assembled from them exactly as from the full table
//! (`crate::bvndf::assemble_lobes`) with the light direction exact instead of interpolated; the
//! clusters of one (light, view node) lie side by side, so all are interpolated in one pass.
//!
//! One geometry's record (`f32`), for `K` clusters, `L` lights and `V` view nodes:
//!
//! | part | length | content |
//! |---|---|---|
//! | clusters | `K × 5` | unit centre (x, y, z), planar flag (0 or 1), area in units of `A_base` |
//! | seen | `V × K × 3` | `G1` of the area seen from `w_b` |
//! | lit | `L × V × K × 9` | `G1`, `G2` (xx, yy, zz, xy, xz, yz) of the area seen from `w_b` and lit from `w_l` |
//!
//! Clusters beyond the geometry's distinct normals have zero area and zero moments.
//!
//! Libraries store the record in half precision ([`crate::lobecodec`]: the header apart, the
//! moments in `f16` about each cluster's centre), and those whose records do not fit in memory
//! may store that form packed ([`crate::lobepack`]: without its zero blocks and the zenith's
//! repeated nodes). All three forms give the same lobes as the numbers they hold.

use crate::bvndf::{assemble_lobes, Clusters, LobeSource, STRIDE};
use crate::error::{Error, Result};
use crate::frame::DirPair;
use crate::frame::Vec3;
use crate::gamma::GammaLayout;
use crate::heightfield::Heightfield;
use crate::lobecodec::{Frame, Local};
use crate::lobepack;
use crate::prefilter::Prefiltered;
use crate::vmf::Vmf;
use half::f16;
use std::borrow::Cow;

/// Floats per cluster in the record's header.
pub(crate) const HEAD: usize = 5;

/// Length of one geometry's record.
pub fn record_len(layout: &GammaLayout, clusters: usize) -> usize {
    let (l, v) = (layout.lights.len(), layout.views.len());
    clusters * (HEAD + v * 3 + l * v * STRIDE)
}

/// The compact BVNDF of one geometry at the library's lights.
#[derive(Debug, Clone)]
pub struct LightLobes<'a> {
    layout: &'a GammaLayout,
    clusters: usize,
    centres: Vec<Vec3>,
    planar: Vec<bool>,
    area: Vec<f64>,
    moments: Moments<'a>,
}

/// A record's moments: the `f32` record itself, or its half-precision form
/// ([`crate::lobecodec`]) with the clusters' frames.
#[derive(Debug, Clone)]
enum Moments<'a> {
    Single(Cow<'a, [f32]>),
    Half {
        body: Cow<'a, [f16]>,
        frames: Vec<Frame>,
        /// For a packed record ([`crate::lobepack`]), where its rows lie in `body`.
        packed: Option<Cow<'a, lobepack::Index>>,
    },
}

impl<'a> LightLobes<'a> {
    /// Trace `hf` with about `rays` view rays per view node and `clusters` normal clusters.
    pub fn build(layout: &'a GammaLayout, hf: &Heightfield, rays: usize, clusters: usize) -> Self {
        let (_, record) = layout.trace(hf, rays, clusters.max(1));
        // The record was just built with this layout: its length and header are right.
        Self::parse(layout, clusters.max(1), Cow::Owned(record))
    }

    /// A stored record (for example a row of a library's `geometry/lobes.bsa`). `what` names it
    /// in errors.
    pub fn from_record(
        layout: &'a GammaLayout,
        clusters: usize,
        record: Cow<'a, [f32]>,
        what: &str,
    ) -> Result<Self> {
        let want = record_len(layout, clusters);
        if clusters == 0 || record.len() != want {
            return Err(Error::new(
                what,
                format!(
                    "a light-lobe record of {} floats does not match {} clusters ({} expected)",
                    record.len(),
                    clusters,
                    want
                ),
            ));
        }
        check_head(&record[..clusters * HEAD], what)?;
        Ok(Self::parse(layout, clusters, record))
    }

    /// A stored record in half precision ([`crate::lobecodec`]): its header `head` (`f32`,
    /// `clusters × 5`) and its moments `body`. `what` names it in errors.
    pub fn from_half(
        layout: &'a GammaLayout,
        clusters: usize,
        head: &[f32],
        body: Cow<'a, [f16]>,
        what: &str,
    ) -> Result<Self> {
        let want = crate::lobecodec::half_len(record_len(layout, clusters), clusters);
        if clusters == 0
            || clusters > MAX_HALF_CLUSTERS
            || head.len() != clusters * HEAD
            || body.len() != want
        {
            return Err(Error::new(
                what,
                format!(
                    "a half-precision light-lobe record of {} + {} numbers does not match {} \
                     clusters ({} + {} expected, at most {MAX_HALF_CLUSTERS} clusters)",
                    head.len(),
                    body.len(),
                    clusters,
                    clusters * HEAD,
                    want
                ),
            ));
        }
        Self::half_moments(layout, clusters, head, body, None, what)
    }

    /// The lobes of a half-precision or packed record whose lengths were checked: its header
    /// is checked, and each cluster's frame made.
    fn half_moments(
        layout: &'a GammaLayout,
        clusters: usize,
        head: &[f32],
        body: Cow<'a, [f16]>,
        packed: Option<Cow<'a, lobepack::Index>>,
        what: &str,
    ) -> Result<Self> {
        check_head(head, what)?;
        let frames = head.chunks(HEAD).map(Frame::of_head).collect();
        Ok(Self::parse_head(
            layout,
            clusters,
            head,
            Moments::Half {
                body,
                frames,
                packed,
            },
        ))
    }

    /// A stored record in the packed form ([`crate::lobepack`]): its header `head` (`f32`,
    /// `clusters × 5`) and its packed words. `what` names it in errors.
    pub fn from_packed(
        layout: &'a GammaLayout,
        clusters: usize,
        head: &[f32],
        words: Cow<'a, [f16]>,
        what: &str,
    ) -> Result<Self> {
        Self::from_packed_indexed(layout, clusters, head, words, None, what)
    }

    /// [`Self::from_packed`] with the record's index made before (by
    /// [`lobepack::Index::new`] on the same words), for a record read many times.
    pub fn from_packed_indexed(
        layout: &'a GammaLayout,
        clusters: usize,
        head: &[f32],
        words: Cow<'a, [f16]>,
        index: Option<&'a lobepack::Index>,
        what: &str,
    ) -> Result<Self> {
        let shape = pack_shape(layout, clusters);
        let index = (clusters > 0 && head.len() == clusters * HEAD)
            .then(|| match index {
                Some(ix) => {
                    (*ix.shape() == shape && ix.words() == words.len()).then_some(Cow::Borrowed(ix))
                }
                None => lobepack::Index::new(&words, &shape).map(Cow::Owned),
            })
            .flatten()
            .ok_or_else(|| {
                Error::new(
                    what,
                    format!(
                        "a packed light-lobe record of {} + {} numbers does not match {} \
                         clusters and its masks (the file is corrupted or of another profile)",
                        head.len(),
                        words.len(),
                        clusters
                    ),
                )
            })?;
        Self::half_moments(layout, clusters, head, words, Some(index), what)
    }

    fn parse(layout: &'a GammaLayout, clusters: usize, record: Cow<'a, [f32]>) -> Self {
        let head = record[..clusters * HEAD].to_vec();
        Self::parse_head(layout, clusters, &head, Moments::Single(record))
    }

    fn parse_head(
        layout: &'a GammaLayout,
        clusters: usize,
        head: &[f32],
        moments: Moments<'a>,
    ) -> Self {
        let centres = head
            .chunks(HEAD)
            .map(|h| {
                let v = Vec3::new(h[0] as f64, h[1] as f64, h[2] as f64);
                if v.norm() > 0.0 {
                    v.normalized()
                } else {
                    Vec3::Z
                }
            })
            .collect();
        let planar = head.chunks(HEAD).map(|h| h[3] > 0.5).collect();
        let area = head.chunks(HEAD).map(|h| h[4] as f64).collect();
        LightLobes {
            layout,
            clusters,
            centres,
            planar,
            area,
            moments,
        }
    }

    /// The `f32` record (`None` for a record read in half precision).
    pub fn record(&self) -> Option<&[f32]> {
        match &self.moments {
            Moments::Single(r) => Some(r),
            Moments::Half { .. } => None,
        }
    }

    /// The half-precision body (`None` for an `f32` or a packed record).
    pub fn half_body(&self) -> Option<&[f16]> {
        match &self.moments {
            Moments::Half {
                body, packed: None, ..
            } => Some(body),
            _ => None,
        }
    }

    /// Bytes of the stored form.
    pub fn bytes(&self) -> usize {
        match &self.moments {
            Moments::Single(r) => r.len() * 4,
            Moments::Half { body, .. } => self.clusters * HEAD * 4 + body.len() * 2,
        }
    }

    /// Where the seen moments at view node `b` start, in the moments' own array.
    #[inline]
    fn seen_at(&self, b: usize) -> usize {
        let head = match self.moments {
            Moments::Single(_) => self.clusters * HEAD,
            Moments::Half { .. } => 0,
        };
        head + b * self.clusters * 3
    }

    /// Where the lit moments of light `l` and view node `b` start (every cluster's, side by
    /// side), in the moments' own array.
    #[inline]
    fn lit_at(&self, l: usize, b: usize) -> usize {
        let nv = self.layout.views.len();
        self.seen_at(nv) + (l * nv + b) * self.clusters * STRIDE
    }
}

/// The shape of `layout`'s records of `clusters` clusters, for [`crate::lobepack`].
pub fn pack_shape(layout: &GammaLayout, clusters: usize) -> lobepack::Shape {
    lobepack::Shape {
        clusters,
        lights: layout.lights.len(),
        views: layout.views.len(),
        n_phi: layout.views.n_phi,
    }
}

/// A record's cluster headers must be finite with non-negative areas.
fn check_head(head: &[f32], what: &str) -> Result<()> {
    for (c, h) in head.chunks(HEAD).enumerate() {
        if h.iter().any(|x| !x.is_finite()) || h[4] < 0.0 {
            return Err(Error::new(
                what,
                format!("cluster {c} has a non-finite centre or a negative area"),
            ));
        }
    }
    Ok(())
}

/// Where one pair falls in a light-lobe table: its light and its view-node weights. The same
/// for every geometry of a library, so a search that evaluates many at the same pairs finds
/// it once ([`LightPairs`]).
#[derive(Debug, Clone, Copy)]
pub struct Node {
    light: usize,
    views: [(usize, f64); 4],
}

impl Node {
    /// `None` where `wi` is not one of the layout's lights or `wo` is at or below the horizon.
    pub fn find(layout: &GammaLayout, wi: Vec3, wo: Vec3) -> Option<Self> {
        if wo.z <= 0.0 {
            return None;
        }
        Some(Node {
            light: layout.light_index(wi)?,
            views: layout.views.weights(wo),
        })
    }
}

/// Direction pairs with their [`Node`]s, for evaluating many geometries of one library at them.
#[derive(Debug, Clone)]
pub struct LightPairs {
    pub pairs: Vec<DirPair>,
    nodes: Vec<Option<Node>>,
    /// The pairs' indices sorted by where their data lies in a record (light, then first view
    /// node): evaluated in this order, a geometry's record is read front to back, block after
    /// nearby block, instead of at random (the re-rank of a search reads thousands of records
    /// that are not in the processor's caches).
    order: Vec<usize>,
    /// The pair visited after each pair in `order` (none after the last): while one pair's
    /// lobes are assembled, the next one's blocks are prefetched.
    next: Vec<Option<usize>>,
    /// Where the pairs read the same rows of a record many times (a solve's samples: each
    /// (light, view node) row is read by two or more pairs), the rows they read, each converted
    /// once per record ([`RowPlan`]); `None` where most rows are read once (a coarse pass).
    plan: Option<RowPlan>,
}

/// The distinct rows of a record that a set of pairs reads, and which of them each pair's view
/// nodes read: a half-precision record's rows are then converted to `f32` (and its lit rows
/// multiplied by their areas) once per record rather than once per pair and node, and the
/// pairs add up the converted rows in the same order as before, so every value is the same
/// bit for bit.
#[derive(Debug, Clone)]
struct RowPlan {
    /// The distinct (light, view node) lit rows, in the record's order.
    lit: Vec<(usize, usize)>,
    /// The distinct view nodes' seen rows, in the record's order.
    seen: Vec<usize>,
    /// Per pair, per view node of its [`Node`]: its lit row's and its seen row's place in
    /// `lit` and `seen` (meaningless where the node's weight is 0).
    slots: Vec<[(u32, u32); 4]>,
}

impl RowPlan {
    /// The plan of pairs placed at `nodes`, when the rows are read at least
    /// [`PLAN_REUSE`] times on average.
    fn new(nodes: &[Option<Node>]) -> Option<Self> {
        use std::collections::BTreeMap;
        let (mut lit, mut seen) = (BTreeMap::new(), BTreeMap::new());
        let mut reads = 0usize;
        for n in nodes.iter().flatten() {
            for &(b, vb) in &n.views {
                if vb != 0.0 {
                    lit.insert((n.light, b), 0u32);
                    seen.insert(b, 0u32);
                    reads += 2;
                }
            }
        }
        let rows = lit.len() + seen.len();
        if rows == 0 || (reads as f64) < PLAN_REUSE * rows as f64 {
            return None;
        }
        for (i, v) in lit.values_mut().enumerate() {
            *v = i as u32;
        }
        for (i, v) in seen.values_mut().enumerate() {
            *v = i as u32;
        }
        let slots = nodes
            .iter()
            .map(|n| match n {
                Some(n) => n.views.map(|(b, vb)| {
                    if vb == 0.0 {
                        (0, 0)
                    } else {
                        (lit[&(n.light, b)], seen[&b])
                    }
                }),
                None => [(0, 0); 4],
            })
            .collect();
        Some(RowPlan {
            lit: lit.into_keys().collect(),
            seen: seen.into_keys().collect(),
            slots,
        })
    }
}

/// The average number of reads per row at which pairs convert each row once ([`RowPlan`]):
/// converting a row costs about what reading it in place does, and the buffer of converted
/// rows must be written and read again.
const PLAN_REUSE: f64 = 1.5;

/// A record's rows converted once for a [`RowPlan`] (per thread, reused from record to
/// record: a record's rows take a few hundred kilobytes).
#[derive(Default)]
struct Rows {
    /// `plan.lit`'s rows, `clusters × STRIDE` each, multiplied by their areas.
    lit: Vec<f32>,
    /// Their planar clusters' entries in the macro frame (`clusters × STRIDE` per row, empty
    /// for a record without planar clusters).
    ent: Vec<f32>,
    /// `plan.seen`'s rows, `clusters × 3` each.
    seen: Vec<f32>,
}

thread_local! {
    static ROWS: std::cell::RefCell<Rows> = std::cell::RefCell::new(Rows::default());
}

impl LightPairs {
    pub fn new(layout: &GammaLayout, pairs: Vec<DirPair>) -> Self {
        let nodes: Vec<Option<Node>> = pairs
            .iter()
            .map(|p| Node::find(layout, p.wi, p.wo))
            .collect();
        Self::placed(pairs, nodes)
    }

    /// `pairs` at their `nodes`, with the order they are visited in.
    fn placed(pairs: Vec<DirPair>, nodes: Vec<Option<Node>>) -> Self {
        let mut order: Vec<usize> = (0..pairs.len()).collect();
        order.sort_by_key(|&i| match &nodes[i] {
            Some(n) => (
                n.light,
                n.views
                    .iter()
                    .filter(|v| v.1 != 0.0)
                    .map(|v| v.0)
                    .min()
                    .unwrap_or(0),
            ),
            None => (usize::MAX, 0),
        });
        let mut next = vec![None; pairs.len()];
        for w in order.windows(2) {
            next[w[0]] = Some(w[1]);
        }
        let plan = RowPlan::new(&nodes);
        LightPairs {
            pairs,
            nodes,
            order,
            next,
            plan,
        }
    }

    /// `pairs` with each view moved to the view node nearest it (largest cosine): a record is
    /// then read at one node per pair instead of interpolated over up to four. Returns the
    /// moved pairs' placement; its `pairs` are the moved pairs, at which a target must be
    /// read again. Pairs whose light is not one of the layout's, or whose view is at or below
    /// the horizon, are kept as they are (they have no lobes either way).
    pub fn snapped(layout: &GammaLayout, pairs: Vec<DirPair>) -> Self {
        let grid = &layout.views;
        let (pairs, nodes): (Vec<DirPair>, Vec<Option<Node>>) = pairs
            .into_iter()
            .map(|p| match Node::find(layout, p.wi, p.wo) {
                Some(n) => {
                    let b = (0..grid.len())
                        .max_by(|&a, &b| {
                            p.wo.dot(grid.direction(a))
                                .total_cmp(&p.wo.dot(grid.direction(b)))
                                .then(b.cmp(&a))
                        })
                        .unwrap_or(0);
                    let wo = grid.direction(b);
                    let node = Node {
                        light: n.light,
                        views: [(b, 1.0), (b, 0.0), (b, 0.0), (b, 0.0)],
                    };
                    (DirPair { wi: p.wi, wo }, Some(node))
                }
                None => (p, None),
            })
            .unzip();
        Self::placed(pairs, nodes)
    }
}

impl LightLobes<'_> {
    /// `fbar` of `mat` at `at`'s pairs (found with this geometry's layout); equal to
    /// [`crate::fast::fbar`] at the same pairs.
    pub fn fbar(&self, mat: &Prefiltered, at: &LightPairs) -> Vec<f64> {
        self.with_rows(at, |rows| {
            crate::fast::fbar_by(
                mat,
                &at.pairs,
                Some(&at.order),
                self.clusters,
                |i, p, out| self.lobes_of(at, rows, i, p, out),
            )
        })
    }

    /// `f` with this record's rows converted for `at`'s [`RowPlan`] (`None`: `at` has none,
    /// the record is `f32`, or this thread's buffer is in use).
    fn with_rows<T>(&self, at: &LightPairs, f: impl FnOnce(Option<&Rows>) -> T) -> T {
        let (
            Some(plan),
            Moments::Half {
                body,
                frames,
                packed,
            },
        ) = (&at.plan, &self.moments)
        else {
            return f(None);
        };
        ROWS.with(|cell| {
            let mut rows = cell.try_borrow_mut().ok();
            if let Some(r) = rows.as_deref_mut() {
                self.convert_rows(body, frames, packed.as_deref(), plan, r);
            }
            f(rows.as_deref())
        })
    }

    /// The lobes at `at`'s pair `i` (from `rows` when given: `at`'s plan converted).
    #[inline]
    fn lobes_of(
        &self,
        at: &LightPairs,
        rows: Option<&Rows>,
        i: usize,
        p: &DirPair,
        out: &mut Vec<(f64, Vmf)>,
    ) {
        let Some(n) = &at.nodes[i] else {
            out.clear();
            return;
        };
        match (rows, &at.plan, &self.moments) {
            (Some(rows), Some(plan), Moments::Half { frames, .. }) => {
                let src = Source::Rows {
                    rows,
                    slots: &plan.slots[i],
                };
                self.lobes_half(frames, src, n, p.wi, p.wo, out)
            }
            _ => {
                if let Some(Some(n)) = at.next[i].map(|j| &at.nodes[j]) {
                    self.prefetch(n);
                }
                self.lobes_at(n, p.wi, p.wo, out)
            }
        }
    }

    /// Start loading the blocks [`Self::lobes_at`] reads at `n` (a hint; changes nothing).
    /// A search's re-rank reads a few blocks of each of thousands of records that are in no
    /// cache; with the next pair's blocks on their way while this pair's lobes are
    /// assembled, the two overlap.
    #[inline]
    fn prefetch(&self, n: &Node) {
        let k = self.clusters;
        for &(b, vb) in &n.views {
            if vb != 0.0 {
                let (s, l) = (self.seen_at(b), self.lit_at(n.light, b));
                match &self.moments {
                    Moments::Single(r) => {
                        crate::prefetch::read(&r[s..s + k * 3]);
                        crate::prefetch::read(&r[l..l + k * STRIDE]);
                    }
                    Moments::Half {
                        body, packed: None, ..
                    } => {
                        crate::prefetch::read(&body[s..s + k * 3]);
                        crate::prefetch::read(&body[l..l + k * STRIDE]);
                    }
                    Moments::Half {
                        body,
                        packed: Some(ix),
                        ..
                    } => {
                        let sh = ix.shape();
                        crate::prefetch::read(&body[ix.span(sh.seen_row(b))]);
                        crate::prefetch::read(&body[ix.span(sh.lit_row(n.light, b))]);
                    }
                }
            }
        }
    }

    /// The lobes at `at`'s pairs, for evaluating many materials there; equal to
    /// [`crate::fast::FixedLobes::new`] at the same pairs.
    pub fn fixed(&self, at: &LightPairs) -> crate::fast::FixedLobes {
        self.with_rows(at, |rows| {
            crate::fast::FixedLobes::by(&at.pairs, Some(&at.order), self.clusters, |i, p, out| {
                self.lobes_of(at, rows, i, p, out)
            })
        })
    }

    /// The lobes at a pair whose [`Node`] is `n`.
    fn lobes_at(&self, n: &Node, wi: Vec3, wo: Vec3, out: &mut Vec<(f64, Vmf)>) {
        match &self.moments {
            Moments::Single(r) => self.lobes_single(r, n, wi, wo, out),
            Moments::Half {
                body,
                frames,
                packed,
            } => {
                let src = Source::InPlace {
                    body,
                    packed: packed.as_deref(),
                };
                self.lobes_half(frames, src, n, wi, wo, out)
            }
        }
    }

    /// [`assemble_lobes`] at node `n` (light `n.light` exactly, the view nodes' weights):
    /// `entry(b, c)` is cluster `c`'s moments at view node `b` in the macro frame (read for
    /// planar clusters), `blended(c)` its moments interpolated over the view nodes.
    #[allow(clippy::too_many_arguments)]
    fn assemble<'t, M: crate::bvndf::ClusterMoments>(
        &self,
        n: &Node,
        wi: Vec3,
        wo: Vec3,
        entry: &impl Fn(usize, usize) -> &'t [f32],
        blended: impl Fn(usize) -> M,
        diag: f64,
        out: &mut Vec<(f64, Vmf)>,
    ) {
        let cl = Clusters {
            centres: &self.centres,
            planar: &self.planar,
            area: &self.area,
            shapes: &[],
            split: false,
        };
        assemble_lobes(
            &cl,
            wi,
            wo,
            &[(n.light, 1.0)],
            |_| wi,
            &n.views,
            |b| self.layout.views.direction(b),
            &|_, b, c| entry(b, c),
            blended,
            None,
            diag,
            out,
        );
    }

    /// [`Self::lobes_at`] from an `f32` record.
    fn lobes_single(&self, r: &[f32], n: &Node, wi: Vec3, wo: Vec3, out: &mut Vec<(f64, Vmf)>) {
        let (l, wb) = (n.light, &n.views);
        let k = self.clusters;
        let mut diag = 0.0;
        for &(b, vb) in wb {
            if vb == 0.0 {
                continue;
            }
            let s = self.seen_at(b);
            for e in r[s..s + k * 3].chunks_exact(3) {
                diag += vb * (wo.x * e[0] as f64 + wo.y * e[1] as f64 + wo.z * e[2] as f64);
            }
        }
        // Every cluster's lit moments interpolated over the view nodes, in one pass over each
        // node's contiguous block (the order of additions is `bvndf::blend`'s).
        // (Flat, so that the loop runs over whole vector registers.)
        let nl = k * STRIDE;
        let mut stack = [0.0f64; 32 * STRIDE];
        let mut heap = Vec::new();
        let acc: &mut [f64] = if nl <= stack.len() {
            &mut stack[..nl]
        } else {
            heap.resize(nl, 0.0);
            &mut heap
        };
        for &(b, vb) in wb {
            if vb == 0.0 {
                continue;
            }
            let o = self.lit_at(l, b);
            for (a, &e) in acc.iter_mut().zip(&r[o..o + nl]) {
                *a += vb * e as f64;
            }
        }
        let acc = &*acc;
        self.assemble(
            n,
            wi,
            wo,
            &|b, c| {
                let o = self.lit_at(l, b) + c * STRIDE;
                &r[o..o + STRIDE]
            },
            |c| {
                let mut a = [0.0; STRIDE];
                a.copy_from_slice(&acc[c * STRIDE..(c + 1) * STRIDE]);
                a
            },
            diag,
            out,
        );
    }

    /// [`Self::lobes_at`] from a half-precision record: each node's block is converted to
    /// `f32` in one pass (8 numbers per instruction with F16C; [`Self::lit_row`]) or taken
    /// converted from `src`'s rows, the moments are interpolated in each cluster's frame (the
    /// decoding is linear once multiplied by the area) and turned to the macro frame once per
    /// cluster.
    fn lobes_half(
        &self,
        frames: &[Frame],
        src: Source<'_>,
        n: &Node,
        wi: Vec3,
        wo: Vec3,
        out: &mut Vec<(f64, Vmf)>,
    ) {
        let (l, wb) = (n.light, &n.views);
        let k = self.clusters;
        let (ns, nl) = (k * 3, k * STRIDE);
        // Buffers on the stack for up to 16 clusters (the profiles' default), else on the heap.
        const STACK: usize = 16;
        let (mut c0, mut d0, mut s0, mut a0) = (
            [0f32; STACK * STRIDE],
            [0f32; STACK * 3],
            [0f64; STACK * 3],
            [0f64; STACK * STRIDE],
        );
        let (mut c1, mut d1, mut s1, mut a1) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        // `conv` and `sconv`: a node's lit and seen rows converted; `seen` and `acc` their sums.
        let (conv, sconv, seen, acc): (&mut [f32], &mut [f32], &mut [f64], &mut [f64]) =
            if k <= STACK {
                (&mut c0[..nl], &mut d0[..ns], &mut s0[..ns], &mut a0[..nl])
            } else {
                c1.resize(nl, 0.0);
                d1.resize(ns, 0.0);
                s1.resize(ns, 0.0);
                a1.resize(nl, 0.0);
                (&mut c1, &mut d1, &mut s1, &mut a1)
            };
        // A planar cluster is read node by node: its entries in the macro frame (from its lit
        // area alone: its normals are its centre's).
        // Only the nodes of non-zero weight are read: `assemble_lobes` reads no other.
        let planar = self.planar.iter().any(|&p| p);
        let (mut e0, mut e1);
        let ent: &mut [f32] = if !planar {
            &mut []
        } else if k <= STACK {
            e0 = [0f32; 4 * STACK * STRIDE];
            &mut e0[..wb.len() * nl]
        } else {
            e1 = vec![0f32; wb.len() * nl];
            &mut e1
        };
        for (i, &(b, vb)) in wb.iter().enumerate() {
            if vb == 0.0 {
                continue;
            }
            // The node's lit entries multiplied by their areas (exact enough in f32: 2⁻²⁴
            // against f16's 2⁻¹¹), which add up as the f32 records' do, in one flat loop; then
            // its seen entries.
            let (lit, seen_row): (&[f32], &[f32]) = match src {
                Source::InPlace { body, packed } => {
                    let ent = planar.then(|| &mut ent[i * nl..(i + 1) * nl]);
                    self.lit_row(body, frames, packed, l, b, conv, ent);
                    self.seen_row(body, packed, b, sconv);
                    (conv, sconv)
                }
                Source::Rows { rows, slots } => {
                    let (li, si) = (slots[i].0 as usize, slots[i].1 as usize);
                    if planar {
                        ent[i * nl..(i + 1) * nl].copy_from_slice(&rows.ent[li * nl..][..nl]);
                    }
                    (&rows.lit[li * nl..][..nl], &rows.seen[si * ns..][..ns])
                }
            };
            for (a, &e) in acc.iter_mut().zip(lit) {
                *a += vb * e as f64;
            }
            for (x, &y) in seen.iter_mut().zip(seen_row) {
                *x += vb * y as f64;
            }
        }
        let diag: f64 = frames
            .iter()
            .zip(seen.chunks_exact(3))
            .map(|(f, g)| wo.dot(f.seen_global(&[g[0], g[1], g[2]])))
            .sum();
        let (acc, ent) = (&*acc, &*ent);
        self.assemble(
            n,
            wi,
            wo,
            &|b, c| {
                let i = wb.iter().position(|v| v.0 == b && v.1 != 0.0).unwrap_or(0);
                &ent[(i * k + c) * STRIDE..][..STRIDE]
            },
            |c| {
                let mut l = [0.0; STRIDE];
                l.copy_from_slice(&acc[c * STRIDE..(c + 1) * STRIDE]);
                Local {
                    frame: &frames[c],
                    l,
                }
            },
            diag,
            out,
        );
    }

    /// A half-precision record's lit row at light `l` and view node `b` in `conv`
    /// (`clusters × STRIDE`), each cluster's entries after the first multiplied by its first
    /// (its area); with `ent`, the planar clusters' entries in the macro frame there.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn lit_row(
        &self,
        body: &[f16],
        frames: &[Frame],
        packed: Option<&lobepack::Index>,
        l: usize,
        b: usize,
        conv: &mut [f32],
        ent: Option<&mut [f32]>,
    ) {
        use half::slice::HalfFloatSliceExt;
        match packed {
            None => {
                let o = self.lit_at(l, b);
                body[o..o + conv.len()].convert_to_f32_slice(conv);
            }
            Some(ix) => ix.fill(body, ix.shape().lit_row(l, b), conv),
        }
        if let Some(ent) = ent {
            for c in (0..self.clusters).filter(|&c| self.planar[c]) {
                let g = frames[c].planar_global(conv[c * STRIDE] as f64);
                for (x, y) in ent[c * STRIDE..][..STRIDE].iter_mut().zip(g) {
                    *x = y as f32;
                }
            }
        }
        for e in conv.chunks_exact_mut(STRIDE) {
            let a = e[0];
            for x in &mut e[1..] {
                *x *= a;
            }
        }
    }

    /// A half-precision record's seen row at view node `b` in `out` (`clusters × 3`).
    #[inline]
    fn seen_row(&self, body: &[f16], packed: Option<&lobepack::Index>, b: usize, out: &mut [f32]) {
        use half::slice::HalfFloatSliceExt;
        match packed {
            None => {
                let s = self.seen_at(b);
                body[s..s + out.len()].convert_to_f32_slice(out);
            }
            Some(ix) => ix.fill(body, ix.shape().seen_row(b), out),
        }
    }

    /// Every row of `plan` of a half-precision record converted into `rows`, as
    /// [`Self::lobes_half`] converts each where it reads it.
    fn convert_rows(
        &self,
        body: &[f16],
        frames: &[Frame],
        packed: Option<&lobepack::Index>,
        plan: &RowPlan,
        rows: &mut Rows,
    ) {
        let k = self.clusters;
        let (ns, nl) = (k * 3, k * STRIDE);
        let planar = self.planar.iter().any(|&p| p);
        rows.lit.resize(plan.lit.len() * nl, 0.0);
        rows.seen.resize(plan.seen.len() * ns, 0.0);
        rows.ent
            .resize(if planar { plan.lit.len() * nl } else { 0 }, 0.0);
        for (i, &(l, b)) in plan.lit.iter().enumerate() {
            let ent = planar.then(|| &mut rows.ent[i * nl..(i + 1) * nl]);
            let conv = &mut rows.lit[i * nl..(i + 1) * nl];
            self.lit_row(body, frames, packed, l, b, conv, ent);
        }
        for (i, &b) in plan.seen.iter().enumerate() {
            self.seen_row(body, packed, b, &mut rows.seen[i * ns..(i + 1) * ns]);
        }
    }
}

/// Where [`LightLobes::lobes_half`] takes a node's rows from: the record, or its rows
/// converted once ([`RowPlan`]) with the pair's places in them.
#[derive(Clone, Copy)]
enum Source<'r> {
    InPlace {
        body: &'r [f16],
        packed: Option<&'r lobepack::Index>,
    },
    Rows {
        rows: &'r Rows,
        slots: &'r [(u32, u32); 4],
    },
}

/// Clusters a half-precision record may have (the libraries' profiles allow up to 64).
pub const MAX_HALF_CLUSTERS: usize = 64;

impl LobeSource for LightLobes<'_> {
    /// The lobes of `gamma(·; wi, wo)`. Defined only where `wi` is one of the library's lights
    /// (to 1e-9); elsewhere, and at or below the horizon, there are none.
    /// The libraries keep one vMF per cluster: `split` does not apply.
    fn lobes(&self, wi: Vec3, wo: Vec3, _split: bool, out: &mut Vec<(f64, Vmf)>) {
        match Node::find(self.layout, wi, wo) {
            Some(n) => self.lobes_at(&n, wi, wo, out),
            None => out.clear(),
        }
    }

    fn clusters(&self) -> usize {
        self.clusters
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvndf::{BvndfConfig, CompactBvndf};
    use crate::frame::{dir_from_deg, DirPair};
    use crate::generators::parse_generator;
    use crate::material::parse_material;
    use crate::prefilter::{PrefilterConfig, Prefiltered};

    #[test]
    fn flat_patch_is_exact_and_record_length_is_checked() {
        let lay = GammaLayout::new(6, 8, 9);
        let hf = Heightfield::flat(16, 16);
        let ll = LightLobes::build(&lay, &hf, 64, 4);
        assert_eq!(ll.record().map(|r| r.len()), Some(record_len(&lay, 4)));
        let mut out = Vec::new();
        ll.lobes(lay.lights[3], dir_from_deg(50.0, 100.0), false, &mut out);
        let total: f64 = out.iter().map(|x| x.0).sum();
        assert!((total - 1.0).abs() < 1e-6, "{out:?}");
        // Not a library light: no lobes.
        ll.lobes(
            dir_from_deg(1.0, 2.0),
            dir_from_deg(50.0, 100.0),
            false,
            &mut out,
        );
        assert!(out.is_empty());
        let short = ll.record().expect("built in f32")[..10].to_vec();
        let e = LightLobes::from_record(&lay, 4, Cow::Owned(short), "x.bsa row 3").unwrap_err();
        assert!(e.to_string().contains("x.bsa row 3"), "{e}");
    }

    #[test]
    fn agrees_with_the_full_compact_bvndf_at_the_library_lights() {
        let lay = GammaLayout::new(10, 16, 16);
        let pf = Prefiltered::build(
            &parse_material("ggx:alpha=0.1+lambert:albedo=0.1").unwrap(),
            &PrefilterConfig::default(),
        );
        for spec in [
            "bumps:n=48,count=6,radius=8,height=3,seed=2",
            "vgroove:n=48,period=16,depth=4",
        ] {
            let hf = parse_generator(spec).unwrap().build().unwrap();
            let ll = LightLobes::build(&lay, &hf, 1024, 16);
            let full = CompactBvndf::build(&hf, &BvndfConfig::library());
            let pairs: Vec<DirPair> = (0..7)
                .flat_map(|l| {
                    let wi = lay.lights[l];
                    [(20.0, 30.0), (45.0, 170.0), (70.0, 290.0)]
                        .into_iter()
                        .map(move |(t, p)| DirPair {
                            wi,
                            wo: dir_from_deg(t, p),
                        })
                })
                .collect();
            let a = crate::fast::fbar(&ll, &pf, &pairs);
            let b = crate::fast::fbar(&full, &pf, &pairs);
            let fixed = crate::fast::FixedLobes::new(&ll, &pairs).fbar(&pf);
            assert_eq!(a, fixed, "lobes assembled once give the same fbar");
            // Pairs placed once and visited in the records' order (here not the given order:
            // reversed, so the lights run backwards) give each pair its own value.
            let rev: Vec<DirPair> = pairs.iter().rev().copied().collect();
            let at = LightPairs::new(&lay, rev);
            assert!(
                at.order.windows(2).any(|w| w[0] > w[1]),
                "the order is not the given one"
            );
            let want: Vec<f64> = a.iter().rev().copied().collect();
            assert_eq!(ll.fbar(&pf, &at), want);
            assert_eq!(ll.fixed(&at).fbar(&pf), want);
            let rel = crate::bench::relative_rms(&a, &b);
            assert!(
                rel < 0.05,
                "{spec}: light lobes vs full compact BVNDF {rel}"
            );
        }
    }

    /// `n` views at each of the 7 lights, spread from the zenith to `top_deg` in a scrambled
    /// order, `dphi_deg` apart in azimuth.
    fn spread_pairs(lay: &GammaLayout, n: usize, top_deg: f64, dphi_deg: f64) -> Vec<DirPair> {
        (0..7)
            .flat_map(|l| {
                let wi = lay.lights[l];
                (0..n).map(move |k| DirPair {
                    wi,
                    wo: dir_from_deg(
                        top_deg * ((k * 7) % n) as f64 / (n - 1) as f64,
                        dphi_deg * k as f64,
                    ),
                })
            })
            .collect()
    }

    #[test]
    fn the_half_precision_form_gives_the_records_fbar() {
        // Curved clusters (bumps, fBm) and planar ones (V-grooves), under a sharp and a
        // broad glossy material, at the 7 lights and views from the zenith to 85°.
        let lay = GammaLayout::new(10, 16, 16);
        let at = LightPairs::new(&lay, spread_pairs(&lay, 40, 85.0, 9.0));
        for spec in [
            "bumps:n=48,count=6,radius=8,height=3,seed=2",
            "fbm:n=48,amplitude=0.5,seed=3",
            "vgroove:n=48,period=16,depth=4",
        ] {
            let hf = parse_generator(spec).unwrap().build().unwrap();
            let ll = LightLobes::build(&lay, &hf, 1024, 16);
            let rec = ll.record().expect("built in f32");
            let (head, body) = crate::lobecodec::encode(rec, 16, lay.views.len()).unwrap();
            let half = LightLobes::from_half(&lay, 16, &head, Cow::Owned(body), "x").unwrap();
            assert_eq!(half.bytes() * 2, ll.bytes() + 16 * HEAD * 4);
            for m in ["ggx:alpha=0.02,f0=0.9", "ggx:alpha=0.2+lambert:albedo=0.1"] {
                let pf = Prefiltered::build(&parse_material(m).unwrap(), &Default::default());
                let (a, b) = (ll.fbar(&pf, &at), half.fbar(&pf, &at));
                let rel = crate::bench::relative_rms(&b, &a);
                assert!(rel < 5e-4, "{spec}, {m}: half against f32 {rel}");
                assert!(b.iter().all(|x| x.is_finite()));
            }
        }
    }

    /// `spec`'s record (16 clusters, 1024 rays per view node) at `lay`, its half-precision
    /// form, and that form's header and moments.
    fn built_and_half<'a>(
        lay: &'a GammaLayout,
        spec: &str,
    ) -> (LightLobes<'a>, LightLobes<'a>, (Vec<f32>, Vec<f16>)) {
        let hf = parse_generator(spec).unwrap().build().unwrap();
        let ll = LightLobes::build(lay, &hf, 1024, 16);
        let (head, body) =
            crate::lobecodec::encode(ll.record().unwrap(), 16, lay.views.len()).unwrap();
        let half = LightLobes::from_half(lay, 16, &head, Cow::Owned(body.clone()), "x").unwrap();
        (ll, half, (head, body))
    }

    #[test]
    fn snapped_pairs_are_read_at_their_nearest_view_node() {
        // A planar-walled geometry and a curved one, in f32 and in half precision: a pair
        // moved to its nearest node gives the value the record interpolates there.
        let lay = GammaLayout::new(10, 16, 16);
        let pairs = spread_pairs(&lay, 20, 84.0, 17.0);
        let snapped = LightPairs::snapped(&lay, pairs.clone());
        let grid = &lay.views;
        for (p, q) in pairs.iter().zip(&snapped.pairs) {
            assert_eq!(p.wi, q.wi);
            let b = (0..grid.len())
                .position(|b| grid.direction(b) == q.wo)
                .expect("a node's direction");
            for a in 0..grid.len() {
                assert!(p.wo.dot(grid.direction(a)) <= p.wo.dot(grid.direction(b)));
            }
        }
        // Below the horizon: kept, and no lobes.
        let down = DirPair {
            wi: lay.lights[0],
            wo: Vec3::new(0.6, 0.0, -0.8),
        };
        let below = LightPairs::snapped(&lay, vec![down]);
        assert_eq!(below.pairs[0].wo, down.wo);
        let interpolated = LightPairs::new(&lay, snapped.pairs.clone());
        let pf = Prefiltered::build(
            &parse_material("ggx:alpha=0.1+lambert:albedo=0.1").unwrap(),
            &PrefilterConfig::default(),
        );
        for spec in [
            "vgroove:n=48,period=16,depth=4",
            "bumps:n=48,count=6,radius=8,height=3,seed=2",
        ] {
            let (ll, half, _) = built_and_half(&lay, spec);
            for r in [&ll, &half] {
                let (a, b) = (r.fbar(&pf, &snapped), r.fbar(&pf, &interpolated));
                let rel = crate::bench::relative_rms(&a, &b);
                assert!(rel < 1e-9, "{spec}: snapped against interpolated {rel}");
                assert_eq!(r.fbar(&pf, &below), vec![0.0]);
            }
        }
    }

    #[test]
    fn rows_converted_once_give_the_same_bits_as_rows_read_in_place() {
        // Many pairs per light (rows read several times: a plan) and a single pair (no plan);
        // half-precision and packed records of planar and curved clusters.
        let lay = GammaLayout::new(10, 16, 16);
        let many = LightPairs::new(&lay, spread_pairs(&lay, 60, 85.0, 7.0));
        let plan = many.plan.as_ref().expect("rows read many times");
        let reads: usize = many.nodes.iter().flatten().map(|n| n.views.len()).sum();
        assert!(plan.lit.len() < reads);
        let one = LightPairs::new(&lay, many.pairs[..1].to_vec());
        assert!(one.plan.is_none(), "a pair reads each of its rows once");
        let pf = Prefiltered::build(
            &parse_material("ggx:alpha=0.05,f0=0.8+lambert:albedo=0.1").unwrap(),
            &PrefilterConfig::default(),
        );
        let shape = pack_shape(&lay, 16);
        for spec in [
            "vgroove:n=48,period=16,depth=4",
            "bumps:n=48,count=6,radius=8,height=3,seed=2",
        ] {
            let (_, half, (head, body)) = built_and_half(&lay, spec);
            let words = lobepack::pack(&body, &shape).unwrap();
            let packed = LightLobes::from_packed(&lay, 16, &head, Cow::Owned(words), "x").unwrap();
            for r in [&half, &packed] {
                // In place, pair by pair, against the plan's converted rows.
                let in_place = crate::fast::fbar(r, &pf, &many.pairs);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&r.fbar(&pf, &many)), bits(&in_place), "{spec}");
                assert_eq!(bits(&r.fixed(&many).fbar(&pf)), bits(&in_place), "{spec}");
                assert!(in_place.iter().any(|&x| x > 0.0));
            }
        }
    }
}
