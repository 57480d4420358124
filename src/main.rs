//! The `clearview` binary: parses the command line, starts logging, runs the subcommand
//! and turns its outcome into an exit code (0 ok, 1 runtime failure, 3 rejected,
//! 64 bad usage).

use std::process::ExitCode;

use clap::Parser;
use clearview::cli::{Cli, Command, align, check_config, cluster, demo, exit, fill, run};

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { exit::USAGE } else { exit::OK };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    // The service logs its lifecycle (INFO); one-shot commands only what went wrong.
    let service = matches!(
        cli.command,
        Command::Run(_) | Command::Ingest(_) | Command::Worker(_) | Command::Collect(_)
    );
    let default = if service { "info" } else { "warn" };
    init_logging(cli.log_json, default);
    let code = match &cli.command {
        Command::Align(args) => align::run(args),
        Command::Fill(args) => fill::run(args),
        Command::Run(args) => run::run(args),
        Command::Ingest(args) => cluster::ingest(args),
        Command::Worker(args) => cluster::worker(args),
        Command::Collect(args) => cluster::collect(args),
        Command::CheckConfig(args) => check_config::run(args),
        Command::Demo { dir } => demo::run(dir),
    };
    ExitCode::from(code)
}

fn init_logging(json: bool, default: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("CLEARVIEW_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    if json {
        builder.json().init();
    } else {
        builder.with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr())).init();
    }
}
