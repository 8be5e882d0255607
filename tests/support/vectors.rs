//! The maker's golden frames (`tests/vectors/frames.tsv`), parsed once for
//! every test that needs them.

/// The file's text, compiled into the tests.
pub const VECTORS: &str = include_str!("../vectors/frames.tsv");

/// One golden frame.
pub struct Vector {
    /// Its name (first column).
    pub name: String,
    /// `request`, `request+echo` or `response`.
    pub direction: String,
    /// The whole frame, CRC included.
    pub bytes: Vec<u8>,
}

/// Every frame of the file, in order.
pub fn vectors() -> Vec<Vector> {
    VECTORS
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|line| {
            let cols: Vec<&str> = line.split('\t').collect();
            assert!(cols.len() >= 3, "malformed vector line: {line}");
            Vector {
                name: cols[0].to_string(),
                direction: cols[1].to_string(),
                bytes: cols[2]
                    .split_whitespace()
                    .map(|h| u8::from_str_radix(h, 16).unwrap())
                    .collect(),
            }
        })
        .collect()
}

/// The bytes of the frame called `name`.
pub fn vector(name: &str) -> Vec<u8> {
    vectors()
        .into_iter()
        .find(|v| v.name == name)
        .unwrap_or_else(|| panic!("no vector {name}"))
        .bytes
}
