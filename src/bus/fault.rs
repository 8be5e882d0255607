//! What was wrong with one attempt on the wire: a leaf, so the master, the
//! bus errors and the observers above the bus share it without importing
//! one another.

/// What was wrong with one attempt.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Not one byte arrived before the timeout.
    Timeout,
    /// A frame arrived with a bad CRC.
    Crc,
    /// A frame that does not answer the request.
    Mismatch(&'static str),
}

impl Fault {
    /// Text for error messages.
    pub fn describe(&self) -> String {
        match self {
            Fault::Timeout => "no reply".to_string(),
            Fault::Crc => "CRC error".to_string(),
            Fault::Mismatch(what) => what.to_string(),
        }
    }
}
