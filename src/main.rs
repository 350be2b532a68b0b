use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let cli = flownav::cli::Cli::parse();
    // SAFETY: first thing after parsing the arguments; no thread has been started.
    unsafe { flownav::cli::output::quiet_gpu_loaders(cli.verbose) };
    flownav::cli::init_tracing(cli.verbose);
    match flownav::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::from(flownav::cli::exit_code(&err))
        }
    }
}
