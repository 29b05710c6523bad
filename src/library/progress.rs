//! Progress reporting for long library steps, on standard error: bars with rate and ETA and
//! spinners naming the current stage when standard error is a terminal; plain lines (every ~10 %
//! of a bar, with rate and ETA, and one line per stage) when it is not, so cluster logs show
//! progress; nothing at all with `--quiet`.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy)]
pub struct Progress {
    pub quiet: bool,
}

/// One line on standard error. A failed write is ignored (a closed pipe, a full disk): the log
/// is for people, and losing it must not stop the run (`eprintln!` would panic).
pub fn line(msg: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{msg}");
}

/// Where plain lines go: standard error, or (in tests) a list.
#[derive(Clone)]
enum Sink {
    Stderr,
    #[allow(dead_code)]
    Capture(Arc<Mutex<Vec<String>>>),
}

impl Sink {
    fn line(&self, s: String) {
        match self {
            Sink::Stderr => line(&s),
            Sink::Capture(v) => {
                if let Ok(mut v) = v.lock() {
                    v.push(s);
                }
            }
        }
    }
}

/// `4.2 s`, `42 s`, `3m 05s`, `1h 02m`.
pub fn fmt_secs(s: f64) -> String {
    if !s.is_finite() {
        return "?".into();
    }
    if s < 9.95 {
        return format!("{:.1} s", s.max(0.0));
    }
    let s = s.round() as u64;
    if s < 60 {
        format!("{s} s")
    } else if s < 3600 {
        format!("{}m {:02}s", s / 60, s % 60)
    } else {
        format!("{}h {:02}m", s / 3600, (s % 3600) / 60)
    }
}

/// A bar that prints a plain line each time it crosses another tenth of its length.
struct Plain {
    what: String,
    len: AtomicU64,
    pos: AtomicU64,
    /// Tenths already reported; changed only under `printing`.
    reported: AtomicU64,
    /// Held while a line is decided and printed, so that lines come out in the order of their
    /// counts: two threads that each crossed a tenth could otherwise print 5 before 4.
    printing: Mutex<()>,
    start: Instant,
    sink: Sink,
}

impl Plain {
    fn inc(&self, n: u64) {
        let pos = self.pos.fetch_add(n, Ordering::Relaxed) + n;
        let len = self.len.load(Ordering::Relaxed);
        if (pos.min(len) * 10) / len.max(1) <= self.reported.load(Ordering::Relaxed) {
            return;
        }
        let Ok(_printing) = self.printing.lock() else {
            return;
        };
        // The count as it stands now, under the lock: each line's count is at least the one
        // before it.
        let (pos, len) = (
            self.pos.load(Ordering::Relaxed).max(pos),
            self.len.load(Ordering::Relaxed),
        );
        let tenth = (pos.min(len) * 10) / len.max(1);
        if tenth > self.reported.load(Ordering::Relaxed) {
            self.reported.store(tenth, Ordering::Relaxed);
            self.sink.line(self.line(pos));
        }
    }

    /// `n` more items: the tenths are counted again from where the bar now stands.
    fn inc_length(&self, n: u64) {
        let Ok(_printing) = self.printing.lock() else {
            return;
        };
        let len = self.len.fetch_add(n, Ordering::Relaxed) + n;
        let pos = self.pos.load(Ordering::Relaxed);
        self.reported
            .store((pos.min(len) * 10) / len.max(1), Ordering::Relaxed);
    }

    fn line(&self, pos: u64) -> String {
        let len = self.len.load(Ordering::Relaxed);
        let pos = pos.min(len);
        let el = self.start.elapsed().as_secs_f64();
        let rate = pos as f64 / el.max(1e-9);
        let eta = (len - pos) as f64 / rate;
        format!(
            "{}: {pos}/{} ({}%), {:.2}/s, ETA {}, elapsed {}",
            self.what,
            len,
            pos * 100 / len.max(1),
            rate,
            if pos == len {
                "0.0 s".into()
            } else {
                fmt_secs(eta)
            },
            fmt_secs(el)
        )
    }

    fn finish(&self) {
        let Ok(_printing) = self.printing.lock() else {
            return;
        };
        // Report the end unless the last tenth was already reported.
        if self.reported.swap(10, Ordering::Relaxed) < 10 {
            self.sink.line(self.line(self.pos.load(Ordering::Relaxed)));
        }
    }
}

enum BarKind {
    Hidden,
    Term(ProgressBar),
    Plain(Plain),
}

/// A progress bar over a known number of items (safe to advance from many threads).
pub struct Bar(BarKind);

impl Bar {
    pub fn hidden() -> Self {
        Bar(BarKind::Hidden)
    }

    pub fn inc(&self, n: u64) {
        match &self.0 {
            BarKind::Hidden => {}
            BarKind::Term(b) => b.inc(n),
            BarKind::Plain(p) => p.inc(n),
        }
    }

    pub fn finish(&self) {
        match &self.0 {
            BarKind::Hidden => {}
            BarKind::Term(b) => b.finish(),
            BarKind::Plain(p) => p.finish(),
        }
    }

    /// `n` more items than the bar was made for (work found on the way).
    pub fn inc_length(&self, n: u64) {
        match &self.0 {
            BarKind::Hidden => {}
            BarKind::Term(b) => b.inc_length(n),
            BarKind::Plain(p) => p.inc_length(n),
        }
    }
}

enum StagesKind {
    Hidden,
    Term(ProgressBar),
    Plain(Sink),
}

/// A sequence of named stages of unknown length: a spinner showing the current one on a
/// terminal, or a plain line when each starts; every finished stage leaves a line with its time.
pub struct Stages {
    prefix: String,
    kind: StagesKind,
    current: Mutex<Option<(String, Instant)>>,
}

impl Stages {
    fn emit(&self, s: String) {
        match &self.kind {
            StagesKind::Hidden => {}
            StagesKind::Term(b) => b.println(s),
            StagesKind::Plain(sink) => sink.line(s),
        }
    }

    fn end_current(&self) {
        let prev = self.current.lock().ok().and_then(|mut c| c.take());
        if let Some((msg, t)) = prev {
            self.emit(format!(
                "{}: {msg}: done in {}",
                self.prefix,
                fmt_secs(t.elapsed().as_secs_f64())
            ));
        }
    }

    /// End the current stage (if any) and start `msg`.
    pub fn stage(&self, msg: &str) {
        self.end_current();
        match &self.kind {
            StagesKind::Hidden => {}
            StagesKind::Term(b) => b.set_message(format!("{}: {msg}", self.prefix)),
            StagesKind::Plain(sink) => sink.line(format!("{}: {msg} ...", self.prefix)),
        }
        if let Ok(mut c) = self.current.lock() {
            *c = Some((msg.to_string(), Instant::now()));
        }
    }

    /// Report how far the current stage has got (`msg`): a plain line, or the spinner's
    /// message on a terminal.
    pub fn step(&self, msg: &str) {
        let stage = self.current.lock().ok().and_then(|c| {
            c.as_ref()
                .map(|(m, t)| (m.clone(), t.elapsed().as_secs_f64()))
        });
        let Some((stage, secs)) = stage else { return };
        let line = format!(
            "{}: {stage}: {msg} (elapsed {})",
            self.prefix,
            fmt_secs(secs)
        );
        match &self.kind {
            StagesKind::Hidden => {}
            StagesKind::Term(b) => b.set_message(line),
            StagesKind::Plain(sink) => sink.line(line),
        }
    }

    /// End the current stage and remove the spinner.
    pub fn finish(&self) {
        self.end_current();
        if let StagesKind::Term(b) = &self.kind {
            b.finish_and_clear();
        }
    }
}

impl Progress {
    fn plain(&self) -> bool {
        !std::io::stderr().is_terminal()
    }

    /// A bar over `len` items; hidden when quiet or when there is nothing to do.
    pub fn bar(&self, len: u64, what: &str) -> Bar {
        if self.quiet || len == 0 {
            return Bar::hidden();
        }
        if self.plain() {
            return Bar(BarKind::Plain(plain_bar(len, what, Sink::Stderr)));
        }
        let b = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
        if let Ok(style) = ProgressStyle::with_template(
            "{msg:28} [{bar:30}] {pos}/{len} {per_sec} ETA {eta} (elapsed {elapsed})",
        ) {
            b.set_style(style.progress_chars("=> "));
        }
        b.set_message(what.to_string());
        Bar(BarKind::Term(b))
    }

    /// Stages of one step, each line prefixed with `prefix` (e.g. `merge`); hidden when quiet.
    pub fn stages(&self, prefix: &str) -> Stages {
        let kind = if self.quiet {
            StagesKind::Hidden
        } else if self.plain() {
            StagesKind::Plain(Sink::Stderr)
        } else {
            let b = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
            if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} ({elapsed})") {
                b.set_style(style);
            }
            b.enable_steady_tick(Duration::from_millis(120));
            StagesKind::Term(b)
        };
        Stages {
            prefix: prefix.to_string(),
            kind,
            current: Mutex::new(None),
        }
    }

    /// A one-line log message (suppressed when quiet).
    pub fn note(&self, msg: &str) {
        if !self.quiet {
            line(msg);
        }
    }
}

fn plain_bar(len: u64, what: &str, sink: Sink) -> Plain {
    Plain {
        what: what.to_string(),
        len: AtomicU64::new(len),
        pos: AtomicU64::new(0),
        reported: AtomicU64::new(0),
        printing: Mutex::new(()),
        start: Instant::now(),
        sink,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn captured() -> (Sink, Arc<Mutex<Vec<String>>>) {
        let v = Arc::new(Mutex::new(Vec::new()));
        (Sink::Capture(v.clone()), v)
    }

    #[test]
    fn plain_lines_from_many_threads_never_go_back() {
        // Threads that cross tenths together print in the order of their counts (before the
        // lock, `forward`'s "exact: pairs" once printed 5/10 before 4/10).
        for round in 0..50u64 {
            let (sink, lines) = captured();
            let len = 40 + round;
            let b = Bar(BarKind::Plain(plain_bar(len, "pairs", sink)));
            std::thread::scope(|s| {
                for t in 0..4 {
                    let b = &b;
                    s.spawn(move || {
                        for _ in (t..len).step_by(4) {
                            b.inc(1);
                        }
                    });
                }
            });
            b.finish();
            let counts: Vec<u64> = lines
                .lock()
                .unwrap()
                .iter()
                .map(|l| {
                    l["pairs: ".len()..]
                        .split('/')
                        .next()
                        .unwrap()
                        .parse()
                        .unwrap()
                })
                .collect();
            assert!(counts.windows(2).all(|w| w[0] < w[1]), "{counts:?}");
            assert_eq!(counts.last(), Some(&len), "{counts:?}");
        }
    }

    #[test]
    fn plain_bars_print_a_line_every_tenth_with_rate_and_eta() {
        for len in [100u64, 37, 10, 3] {
            let (sink, lines) = captured();
            let b = Bar(BarKind::Plain(plain_bar(len, "geometries", sink)));
            for _ in 0..len {
                b.inc(1);
            }
            b.finish();
            let lines = lines.lock().unwrap();
            let want = len.min(10) as usize;
            assert_eq!(lines.len(), want, "len {len}: {lines:?}");
            assert!(lines[0].starts_with("geometries: "), "{}", lines[0]);
            assert!(lines[0].contains("/s, ETA "), "{}", lines[0]);
            assert!(
                lines[want - 1].contains(&format!("{len}/{len} (100%)")),
                "{}",
                lines[want - 1]
            );
        }
        // A bar that grows on the way reports the new length, and counts tenths of it again.
        let (sink, lines) = captured();
        let b = Bar(BarKind::Plain(plain_bar(10, "directions", sink)));
        for _ in 0..10 {
            b.inc(1);
        }
        b.inc_length(10);
        for _ in 0..10 {
            b.inc(1);
        }
        b.finish();
        let lines = lines.lock().unwrap();
        assert_eq!(lines.len(), 15, "{lines:?}");
        assert!(lines[9].contains("10/10 (100%)"), "{}", lines[9]);
        assert!(lines[10].contains("12/20 (60%)"), "{}", lines[10]);
        assert!(lines[14].contains("20/20 (100%)"), "{}", lines[14]);
        drop(lines);
        // A bar finished early reports where it stopped, once.
        let (sink, lines) = captured();
        let b = Bar(BarKind::Plain(plain_bar(50, "materials", sink)));
        b.inc(3);
        b.finish();
        b.finish();
        let lines = lines.lock().unwrap();
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(lines[0].contains("3/50 (6%)"), "{}", lines[0]);
    }

    #[test]
    fn plain_stages_print_a_line_at_each_start_and_end_and_quiet_prints_nothing() {
        let (sink, lines) = captured();
        let s = Stages {
            prefix: "merge".into(),
            kind: StagesKind::Plain(sink),
            current: Mutex::new(None),
        };
        s.step("before any stage: not printed");
        s.stage("material SVD");
        s.step("pass 1/6");
        s.stage("CX");
        s.finish();
        let lines = lines.lock().unwrap();
        assert_eq!(lines.len(), 5, "{lines:?}");
        assert_eq!(lines[0], "merge: material SVD ...");
        assert!(
            lines[1].starts_with("merge: material SVD: pass 1/6 (elapsed "),
            "{}",
            lines[1]
        );
        assert!(lines[2].starts_with("merge: material SVD: done in "));
        assert_eq!(lines[3], "merge: CX ...");
        assert!(lines[4].starts_with("merge: CX: done in "));
        let q = Progress { quiet: true };
        assert!(matches!(q.bar(10, "x").0, BarKind::Hidden));
        assert!(matches!(q.stages("merge").kind, StagesKind::Hidden));
    }

    #[test]
    fn durations_read_well() {
        assert_eq!(fmt_secs(4.24), "4.2 s");
        assert_eq!(fmt_secs(42.4), "42 s");
        assert_eq!(fmt_secs(185.0), "3m 05s");
        assert_eq!(fmt_secs(3725.0), "1h 02m");
        assert_eq!(fmt_secs(f64::INFINITY), "?");
    }
}
