//! The `drivegate` command: CLI parsing only; the work is in the library.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Puts a bus of RS-485 servo drives on the network.
#[derive(Debug, Parser)]
#[command(name = "drivegate", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Serves a simulated bus of drives on a pty, for third-party tools.
    Sim(drivegate::sim::cli::SimArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("drivegate: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let result = match cli.command {
        Command::Sim(args) => runtime.block_on(drivegate::sim::cli::run(args)),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("drivegate: {e}");
            ExitCode::FAILURE
        }
    }
}
