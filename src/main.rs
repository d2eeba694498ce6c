//! `tessera`: the command line. This file only parses arguments and hands them to the
//! module that runs each subcommand.

mod render_command;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use render::limits::{MAX_AA, MAX_DEPTH, MAX_SIDE};

/// Tessera renders ray-traced images of JSON scenes: spheres, planes, point lights,
/// mirrors and checkerboards.
#[derive(Parser)]
#[command(name = "tessera", version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene file to a PNG image on this machine.
    #[command(
        long_about = "Render a scene file to a PNG image on this machine, using all cores.\n\n\
            The scene is a JSON file (see docs/scene-format.md); its optional \"image\" \
            settings give the size and antialiasing, and the flags below override them. \
            The image is written only when the whole render succeeds.",
        after_help = "Examples:\n  \
            tessera render scenes/seed.json                 writes seed.png here\n  \
            tessera render scenes/seed.json -o big.png --width 1920 --height 1080 --aa 4"
    )]
    Render(RenderArgs),
}

/// Arguments of `tessera render`.
#[derive(clap::Args)]
struct RenderArgs {
    /// The scene file (JSON).
    scene: PathBuf,

    /// Where to write the PNG [default: the scene's file name with .png, in the current
    /// directory].
    #[arg(short, long, value_name = "OUT.png")]
    output: Option<PathBuf>,

    /// Image width in pixels [default: the scene's, else 600].
    #[arg(long, value_name = "W", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    width: Option<u32>,

    /// Image height in pixels [default: the scene's, else 400].
    #[arg(long, value_name = "H", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    height: Option<u32>,

    /// Antialiasing: N gives N x N samples per pixel [default: the scene's, else 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    aa: Option<u32>,

    /// Maximum reflection depth [default: the scene's, else 10].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_DEPTH)))]
    max_depth: Option<u32>,

    /// Rendering threads [default: one per core].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render_command::run(render_command::Options {
            scene: args.scene,
            output: args.output,
            width: args.width,
            height: args.height,
            aa: args.aa,
            max_depth: args.max_depth,
            threads: args.threads,
        }),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
