//! `lightmapd`: the command line (DESIGN §9). `bake` runs the engine on one scene with no
//! server; `example` writes the bundled example scenes; `serve` runs the bake service (API
//! and workers), `worker` runs workers only, `submit` sends a scene to a server, `token`
//! manages the bearer tokens of a server run with `--auth`. Exit
//! codes: 0 success, 2 bad input (unreadable scene, bad option, a 4xx answer), 1 anything
//! else.
//!
//! This file holds the commands' table and the dispatch; each command's options and its
//! body are in `cli/` (one file a command or family: `bake` with `merge`, `serve` with
//! `worker`, `submit`, `token`, `bench`), the pieces they share in `cli/mod.rs`.

mod cli;

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use lightmapd::engine::output::write_atomically;
use lightmapd::engine::scene;

use cli::bake::{BakeArgs, MergeArgs, bake, merge};
use cli::bench::{BenchArgs, bench};
use cli::serve::{ServeArgs, WorkerArgs, serve, worker};
use cli::submit::{SubmitArgs, submit};
use cli::token::{TokenArgs, token};
use cli::{Failure, log_format, quiet_device_select};

#[derive(Parser)]
#[command(name = "lightmapd", version, about = "Bakes lightmaps from glTF scenes")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Bake a lightmap from a .glb or .gltf scene into an EXR file.
    Bake(Box<BakeArgs>),
    /// Measure true error against run time for techniques on the benchmark scenes.
    Bench(BenchArgs),
    /// Write a bundled example scene as .glb.
    Example {
        #[arg(value_enum, default_value = "cornell-box")]
        name: Example,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Run the bake service: HTTP API and a pool of workers, SQLite and a local folder or S3.
    Serve(ServeArgs),
    /// Run workers only, against the database and store of a `serve`.
    Worker(WorkerArgs),
    /// Upload a scene to a server, submit a bake, optionally wait and download the EXR.
    Submit(Box<SubmitArgs>),
    /// Create, list or revoke the bearer tokens of a server run with `--auth`.
    Token(TokenArgs),
    /// Merge the task results of a bake split with `bake --task K/N` into its lightmap.
    Merge(MergeArgs),
}

#[derive(Clone, Copy, ValueEnum)]
enum Example {
    CornellBox,
}

fn main() -> ExitCode {
    quiet_device_select();
    lightmapd::service::install_crypto_provider();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if e.use_stderr() => {
            // Bad options get one line, like every other bad input; clap's usage hints
            // and the "--help" tip are left out.
            let text = e.to_string();
            let line: Vec<&str> = text
                .lines()
                .map(str::trim)
                .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
                .filter(|l| !l.is_empty())
                .collect();
            eprintln!("{}", line.join(" "));
            return ExitCode::from(2);
        }
        Err(e) => e.exit(), // --help and --version
    };
    // The service logs what it does by default; the one-shot commands only warn.
    let default_filter = match cli.command {
        Command::Serve(_) | Command::Worker(_) => "info",
        _ => "warn",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| default_filter.into());
    // Colour codes only for a person; log files and journald get plain text.
    let ansi = std::io::stderr().is_terminal();
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| log_format::Stderr)
        .with_ansi(ansi);
    if matches!(cli.command, Command::Serve(_) | Command::Worker(_)) {
        logs.init();
    } else {
        logs.event_format(log_format::CommandLine::new(ansi)).init();
    }
    let result = match cli.command {
        Command::Serve(args) => serve(args),
        Command::Worker(args) => worker(args),
        Command::Submit(args) => submit(*args),
        Command::Token(args) => token(args),
        Command::Bake(args) => bake(*args),
        Command::Merge(args) => merge(args),
        Command::Bench(args) => bench(args),
        Command::Example {
            name: Example::CornellBox,
            output,
        } => write_atomically(&output, &scene::build::cornell_box().to_glb()).map_err(|e| Failure {
            code: 1,
            message: format!("cannot write {}: {e}", output.display()),
        }),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}
