//! `drivegate sim`: a simulated bus of drives on a pty for third-party tools.

/// Arguments of `drivegate sim`.
#[derive(Debug, Clone, clap::Args)]
pub struct SimArgs {
    /// Where to link the pty (a symlink to /dev/pts/N).
    #[arg(long)]
    pub link: Option<std::path::PathBuf>,
}

/// Runs the simulator until SIGINT/SIGTERM.
pub async fn run(_args: SimArgs) -> std::io::Result<()> {
    Err(std::io::Error::new(
        std::io::ErrorKind::Unsupported,
        "simulator not built yet",
    ))
}
