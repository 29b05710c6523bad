//! Progress reporting for long library steps: bars with rate and ETA on standard error, or
//! nothing at all with `--quiet` (scripts, cluster logs).

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

#[derive(Debug, Clone, Copy)]
pub struct Progress {
    pub quiet: bool,
}

impl Progress {
    /// A bar over `len` items; hidden when quiet or when there is nothing to do.
    pub fn bar(&self, len: u64, what: &str) -> ProgressBar {
        if self.quiet || len == 0 {
            return ProgressBar::hidden();
        }
        let b = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
        if let Ok(style) = ProgressStyle::with_template(
            "{msg:28} [{bar:30}] {pos}/{len} {per_sec} ETA {eta} (elapsed {elapsed})",
        ) {
            b.set_style(style.progress_chars("=> "));
        }
        b.set_message(what.to_string());
        b
    }

    /// A one-line log message (suppressed when quiet).
    pub fn note(&self, msg: &str) {
        if !self.quiet {
            eprintln!("{msg}");
        }
    }
}
