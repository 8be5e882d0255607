//! Empty: this package only names the published crates (Cargo.toml).
