//! `canlift eds check FILE… [--json]`: a CiA 306 linter for EDS and DCF files — what an
//! integrator runs before a site visit. Every defect the import finds is listed with file,
//! line and severity (canopen::eds: a warning was taken as meant, an error left a part out);
//! the exit status is 1 when a file has an error or no usable object, else 0.

use std::path::PathBuf;

use anyhow::bail;
use canopen::eds::{self, Severity};
use serde::Serialize;

/// Command-line arguments of `canlift eds`.
#[derive(Debug, clap::Args)]
pub struct EdsArgs {
    #[command(subcommand)]
    op: EdsOp,
}

#[derive(Debug, clap::Subcommand)]
enum EdsOp {
    /// List every defect of the files, with file, line and severity.
    Check {
        /// EDS or DCF files.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Print JSON: per file its objects and findings.
        #[arg(long)]
        json: bool,
    },
}

/// One file's verdict.
#[derive(Debug, Serialize)]
struct Checked {
    file: String,
    /// Objects usable (0: the file is refused).
    objects: usize,
    findings: Vec<Found>,
}

#[derive(Debug, Serialize)]
struct Found {
    line: usize,
    severity: &'static str,
    message: String,
}

fn check(path: &std::path::Path) -> Checked {
    let file = path.display().to_string();
    match eds::import_file(path, None) {
        Ok(imported) => Checked {
            file,
            objects: imported.description.od.objects().count(),
            findings: imported
                .findings
                .into_iter()
                .map(|f| Found {
                    line: f.line,
                    severity: f.severity.name(),
                    message: f.message,
                })
                .collect(),
        },
        Err(e) => Checked {
            file,
            objects: 0,
            findings: vec![Found {
                line: e.line,
                severity: Severity::Error.name(),
                message: e.reason,
            }],
        },
    }
}

/// Run `canlift eds check`.
pub fn run(args: EdsArgs) -> anyhow::Result<()> {
    let EdsOp::Check { files, json } = args.op;
    let checked: Vec<Checked> = files.iter().map(|f| check(f)).collect();
    if json {
        println!("{}", serde_json::to_string_pretty(&checked)?);
    } else {
        for c in &checked {
            for f in &c.findings {
                println!("{}:{}: {}: {}", c.file, f.line, f.severity, f.message);
            }
            let count = |s: Severity| c.findings.iter().filter(|f| f.severity == s.name()).count();
            println!(
                "{}: {} usable objects, {} errors, {} warnings",
                c.file,
                c.objects,
                count(Severity::Error),
                count(Severity::Warning)
            );
        }
    }
    let failed = checked
        .iter()
        .filter(|c| {
            c.objects == 0
                || c.findings
                    .iter()
                    .any(|f| f.severity == Severity::Error.name())
        })
        .count();
    if failed > 0 {
        bail!("{failed} of {} files have errors", checked.len());
    }
    Ok(())
}
