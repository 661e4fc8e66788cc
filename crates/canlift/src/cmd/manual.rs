//! `canlift completions SHELL` and `canlift manpages DIR`: what a package installs beside the
//! binary (docs/OPERATIONS.md §Package), made from the command-line definition itself so that
//! they never drift from it.

use std::path::Path;

use anyhow::Context;

/// Write `shell`'s completion script for `command` to standard output.
pub fn completions(shell: clap_complete::Shell, mut command: clap::Command) -> anyhow::Result<()> {
    use std::io::Write;
    let name = command.get_name().to_owned();
    // Made in memory first: clap_complete panics where a write fails (a full disk). A reader
    // that goes away ends the command by SIGPIPE, as it ends every printing command (main.rs).
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut command, name, &mut script);
    std::io::stdout()
        .write_all(&script)
        .context("writing the completions")
}

/// Write `canlift.1` and a page per subcommand (`canlift-cloud.1`, `canlift-cloud-user.1`, …)
/// into `dir`, which must exist.
pub fn pages(command: clap::Command, dir: &Path) -> anyhow::Result<()> {
    clap_mangen::generate_to(command, dir)
        .with_context(|| format!("writing manual pages into {}", dir.display()))
}
