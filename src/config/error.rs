//! Configuration errors, each pointing at a line and column.

use std::ops::Range;

/// Why a configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// File path.
        path: String,
        /// What the system said.
        source: std::io::Error,
    },
    /// Not valid TOML, an unknown key, or a value of the wrong type or range.
    #[error("{origin}:{line}:{column}: {message}")]
    Parse {
        /// File (or "built-in default").
        origin: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// Valid TOML that does not make a working setup.
    #[error("{origin}:{line}:{column}: {message}")]
    Invalid {
        /// File (or "built-in default").
        origin: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        message: String,
    },
}

/// 1-based line and column of byte `offset` in `text`.
pub(super) fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let before = &text[..text.floor_char_boundary(offset)];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

impl ConfigError {
    pub(super) fn parse(origin: &str, text: &str, error: &toml::de::Error) -> Self {
        let raw = error.message().trim();
        let ((line, column), message) = match error.span() {
            Some(span) => (
                line_column(text, span.start),
                super::wording::plain(text, span.start, raw),
            ),
            None => ((1, 1), raw.to_string()),
        };
        ConfigError::Parse {
            origin: origin.to_string(),
            line,
            column,
            message,
        }
    }

    pub(super) fn invalid(origin: &str, text: &str, span: Range<usize>, message: String) -> Self {
        let (line, column) = line_column(text, span.start);
        ConfigError::Invalid {
            origin: origin.to_string(),
            line,
            column,
            message,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::line_column;

    #[test]
    fn positions() {
        let text = "a = 1\nbb = 2\n";
        assert_eq!(line_column(text, 0), (1, 1));
        assert_eq!(line_column(text, 6), (2, 1));
        assert_eq!(line_column(text, 11), (2, 6));
        assert_eq!(line_column(text, 999), (3, 1));
    }
}
