//! Errors that reach the user: every message names the input (a file, a command-line argument or a
//! spec string), the field, and what was expected. Nothing in the library panics on bad input.

use std::fmt;

/// One user-facing error. `context` says where (a file path, "--material", a CSV line), `message`
/// says what was wrong and what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct Error {
    pub context: String,
    pub message: String,
}

impl Error {
    pub fn new(context: impl Into<String>, message: impl Into<String>) -> Self {
        Error {
            context: context.into(),
            message: message.into(),
        }
    }

    /// An I/O error on `path`, with the operation that failed.
    pub fn io(path: &std::path::Path, what: &str, err: std::io::Error) -> Self {
        Error::new(path.display().to_string(), format!("cannot {what}: {err}"))
    }

    /// Prefix the context, e.g. turn "alpha: ..." into "--material: alpha: ...".
    pub fn within(mut self, outer: impl fmt::Display) -> Self {
        self.context = if self.context.is_empty() {
            outer.to_string()
        } else {
            format!("{outer}: {}", self.context)
        };
        self
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.context.is_empty() {
            write!(f, "{}", self.message)
        } else {
            write!(f, "{}: {}", self.context, self.message)
        }
    }
}

impl std::error::Error for Error {}

pub type Result<T> = std::result::Result<T, Error>;

/// A number as an error message shows it: as written for ordinary magnitudes, in scientific
/// notation for extreme ones (`1e308`, not 309 digits).
pub fn show_num(v: f64) -> String {
    let a = v.abs();
    if v.is_finite() && v != 0.0 && !(1e-9..1e15).contains(&a) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn extreme_numbers_are_shown_short() {
        use super::show_num;
        assert_eq!(show_num(1e308), "1e308");
        assert_eq!(show_num(-1e-308), "-1e-308");
        assert_eq!(show_num(0.02787), "0.02787");
        assert_eq!(show_num(1.5), "1.5");
        assert_eq!(show_num(0.0), "0");
        assert_eq!(show_num(f64::NAN), "NaN");
    }
}
