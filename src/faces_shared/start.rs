//! What the daemon hands each face it starts, in one piece: so a face's
//! `start` names what it uses, and a new face takes the same.

use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::control::Control;
use crate::history::History;
use crate::metrics::Metrics;
use crate::plant::Plant;

/// The running configuration, the plant, the control core, the metrics
/// and the history, and the face's own stop (a child of the daemon's, so
/// a reload can stop one face alone).
pub(crate) struct FaceStart {
    /// The configuration the face starts with.
    pub(crate) config: Arc<Config>,
    /// The buses and the drive directory (reads).
    pub(crate) plant: Arc<Plant>,
    /// The one write path.
    pub(crate) control: Control,
    /// Where the face counts.
    pub(crate) metrics: Arc<Metrics>,
    /// The trends.
    pub(crate) history: Arc<History>,
    /// Fires when the face is to stop.
    pub(crate) stop: CancellationToken,
}
