//! The `drivegate` command: CLI parsing only; the work is in the library.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use drivegate::config::Config;

/// Puts a bus of RS-485 servo drives (Modbus RTU) on the network.
///
/// Its faces: a REST API with a WebSocket stream, Modbus TCP and
/// Modbus/TCP Security for SCADA and PLCs, an OPC UA server, MQTT
/// (Sparkplug B, or JSON topics), Prometheus metrics, and a web console for
/// people (at / on the API's port). Every write, from any face, passes the same safety rules
/// and is logged. Without hardware it runs on its built-in simulator.
#[derive(Debug, Parser)]
#[command(name = "drivegate", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Runs the daemon and its faces (without --config: one simulated bus
    /// of 4 drives, everything on loopback).
    Serve {
        /// Configuration file (TOML).
        #[arg(long, short)]
        config: Option<PathBuf>,
    },
    /// Checks a configuration file and exits (0 when valid).
    CheckConfig {
        /// Configuration file (TOML).
        file: PathBuf,
    },
    /// Serves a simulated bus of drives on a pty, for third-party tools.
    Sim(drivegate::sim::cli::SimArgs),
    /// Measures status polling and command latency against the wire's limit.
    Bench(drivegate::bench::BenchArgs),
    /// Finds the drives on a line, without configuration, and says what
    /// silence or garbage usually means on RS-485.
    Probe(drivegate::probe::ProbeArgs),
    /// API tokens.
    #[command(subcommand)]
    Token(TokenCommand),
}

#[derive(Debug, Subcommand)]
enum TokenCommand {
    /// Makes a new random token: prints it once, and the [[http.token]]
    /// lines (its SHA-256) to paste into the configuration.
    New {
        /// The name the audit log gives the token's writes.
        #[arg(long)]
        name: String,
        /// viewer, operator or admin.
        #[arg(long)]
        role: String,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::CheckConfig { file } => check_config(&file),
        Command::Serve { config } => serve(config),
        Command::Bench(args) => run(|| drivegate::bench::run(args)),
        Command::Probe(args) => run(|| drivegate::probe::run(args)),
        Command::Token(TokenCommand::New { name, role }) => new_token(&name, &role),
        Command::Sim(args) => run(|| async move {
            drivegate::sim::cli::run(args)
                .await
                .map_err(|e| e.to_string())
        }),
    }
}

fn check_config(file: &std::path::Path) -> ExitCode {
    let loaded = Config::load_with_warnings(file)
        .map_err(|e| e.to_string())
        .and_then(|(c, warnings)| {
            drivegate::api::config_check::check_tls(&c)
                .map_err(|e| format!("{}: {e}", file.display()))?;
            Ok((c, warnings))
        });
    match loaded {
        Ok((c, warnings)) => {
            // Valid, so the exit status stays 0; a script sees them on stderr.
            for warning in &warnings {
                eprintln!("warning: {warning}");
            }
            println!(
                "{}: valid ({} bus(es), {} drive(s))",
                file.display(),
                c.buses.len(),
                c.drive_count()
            );
            if c.buses.is_empty() {
                println!("no bus configured: `drivegate probe --port PATH` finds the drives");
            }
            for (warning, text) in c.modbus_tcp.notices(c.modbus_tcp.listen) {
                println!("{}{text}", if warning { "warning: " } else { "note: " });
            }
            match c.safety.state_dir() {
                Some(dir) => match drivegate::control::journal::check_writable(&dir) {
                    Ok(()) => println!("safety journal: {} is writable", dir.display()),
                    Err(e) => {
                        eprintln!("{e}");
                        return ExitCode::FAILURE;
                    }
                },
                None => println!(
                    "safety journal: none ([safety] state_dir unset and no $STATE_DIRECTORY): leases are not kept across a restart"
                ),
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("{e}");
            ExitCode::FAILURE
        }
    }
}

fn new_token(name: &str, role: &str) -> ExitCode {
    match drivegate::api::new_token::generate(name, role) {
        Ok(made) => {
            println!("Token (shown only now; give it to the client, keep it secret):");
            println!();
            println!("    {}", made.token);
            println!();
            println!("{}", drivegate::api::new_token::FIRST_TOKEN_NOTE);
            if role != "admin" {
                println!("{}", drivegate::api::new_token::MAKE_AN_ADMIN);
            }
            println!();
            println!("Add these lines to the configuration (they hold only the token's SHA-256),");
            println!("then reload drivegate (systemctl reload drivegate):");
            println!();
            print!("{}", made.config);
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("drivegate: {e}");
            ExitCode::FAILURE
        }
    }
}

fn serve(path: Option<PathBuf>) -> ExitCode {
    let config = match &path {
        Some(p) => Config::load_with_warnings(p),
        None => Config::embedded_default().map(|c| (c, Vec::new())),
    };
    let (mut config, warnings) = match config {
        Ok(c) => c,
        Err(e) => {
            eprintln!("drivegate: {e}");
            return ExitCode::FAILURE;
        }
    };
    if path.is_none() && config.safety.state_dir().is_none() {
        // The simulated plant of `serve` alone keeps its journal where the
        // README says: the user's state directory.
        config.safety.state_dir = Some(drivegate::control::journal::default_dir());
    }
    if let Some(note) = drivegate::logging::init(&config.log) {
        tracing::warn!("{note}");
    }
    for warning in warnings {
        tracing::warn!("{warning}");
    }
    if path.is_none() {
        tracing::info!(
            "no --config given: running the built-in configuration (one simulated bus of 4 drives)"
        );
    }
    run(|| async move {
        drivegate::daemon::serve(config, path)
            .await
            .map_err(|e| e.to_string())
    })
}

/// Runs `f` on a multi-threaded runtime and maps its result to an exit code.
fn run<F, Fut>(f: F) -> ExitCode
where
    F: FnOnce() -> Fut,
    Fut: std::future::Future<Output = Result<(), String>>,
{
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("drivegate: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(f()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            eprintln!("drivegate: {e}");
            ExitCode::FAILURE
        }
    }
}
