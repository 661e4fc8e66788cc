//! `canlift-bench portal --phases curves`: how the portal's costs grow (docs/BENCHMARKS.md
//! §Growth curves). Three sweeps on one portal process — its memory while gateways come
//! online step by step, the reconnect storm's time against the number of gateways (new TLS
//! sessions and resumed ones), values stored per second against the number of pushing
//! gateways — each written as CSV and drawn as SVG into `--curves DIR`. (`canlift-bench
//! gateway --curves DIR` adds the gateway's latency against subscriptions held.)

use std::path::Path;
use std::time::Duration;

use super::{fleet_args, ingest, portal_online, storm_once, PortalBench, PortalProcess};
use crate::plot::{Curve, Series};
use crate::process::mib;
use gateway::fleet::Fleet;

/// The three sweeps, up to `args.gateways` gateways; files into `out`.
pub(super) async fn curves(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
    out: &Path,
) -> anyhow::Result<()> {
    let steps = steps(args.gateways);
    let memory = memory_curve(args, portal, dir, &steps).await?;
    memory.write(out)?;
    // The memory sweep made every gateway's first contact: the storms are of known gateways.
    storm_curve(args, portal, dir, &steps).await?.write(out)?;
    ingest_curve(args, portal, dir).await?.write(out)?;
    println!("curves                CSV and SVG in {}", out.display());
    Ok(())
}

/// 1,000, 2,000, then every 2,000 up to `max` (and `max` itself).
fn steps(max: usize) -> Vec<usize> {
    let mut steps: Vec<usize> = [1000, 2000]
        .into_iter()
        .chain((4000..max).step_by(2000))
        .filter(|n| *n < max)
        .collect();
    steps.push(max);
    steps
}

/// The portal's RSS with 0 gateways, then with each step's number online (added at
/// `args.rate` first contacts per second and held).
async fn memory_curve(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
    steps: &[usize],
) -> anyhow::Result<Curve> {
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut points = vec![(0.0, mib(portal.rss_kib()))];
    let mut fleets = Vec::new();
    let mut online = 0;
    for &target in steps {
        let mut more = fleet_args(args, portal, dir, target - online);
        more.first = online + 1;
        more.rate = args.rate;
        let fleet = Fleet::start(&more, None).await?;
        fleet
            .all_online(fleet.launched(), Duration::from_secs(600))
            .await?;
        fleets.push(fleet);
        online = target;
        portal_online(portal, online, Duration::from_secs(60)).await?;
        // The first contacts' token writes and dashboard subscriptions settle.
        tokio::time::sleep(Duration::from_secs(3)).await;
        let rss = mib(portal.rss_kib());
        println!("portal memory         {online} gateways online: RSS {rss:.1} MiB");
        points.push((online as f64, rss));
    }
    for fleet in fleets {
        fleet.stop().await;
    }
    portal_online(portal, 0, Duration::from_secs(60)).await?;
    Ok(Curve {
        name: "portal-memory",
        title: "Portal memory vs idle TLS gateways",
        x: "gateways online",
        y: "portal RSS (MiB)",
        series: vec![Series {
            name: "RSS",
            points,
        }],
    })
}

/// Each step's number of known gateways reconnecting at once: with new TLS sessions, then
/// resuming the sessions of that storm.
async fn storm_curve(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
    steps: &[usize],
) -> anyhow::Result<Curve> {
    let (mut full, mut resumed) = (Vec::new(), Vec::new());
    for &n in steps {
        let mut storm = args.clone();
        storm.storm = n;
        let (sessions, took) = storm_once(&storm, portal, dir, None, "new TLS sessions").await?;
        full.push((n as f64, took.as_secs_f64()));
        let (_, took) = storm_once(&storm, portal, dir, Some(sessions), "resuming").await?;
        resumed.push((n as f64, took.as_secs_f64()));
    }
    Ok(Curve {
        name: "reconnect-storm",
        title: "Reconnect storm: time until every gateway has CONNACK",
        x: "gateways reconnecting at once",
        y: "seconds",
        series: vec![
            Series {
                name: "new TLS sessions",
                points: full,
            },
            Series {
                name: "resumed sessions",
                points: resumed,
            },
        ],
    })
}

/// Values stored per second with more and more gateways pushing (each changing its values
/// every `args.change_ms`).
async fn ingest_curve(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
) -> anyhow::Result<Curve> {
    let mut points = Vec::new();
    for pushers in [50, 100, 250, 500, 1000, 2000] {
        let mut ingest_args = args.clone();
        ingest_args.pushers = pushers;
        let stored = ingest(&ingest_args, portal, dir).await?;
        points.push((pushers as f64, stored));
    }
    Ok(Curve {
        name: "ingest",
        title: "Values stored per second vs pushing gateways",
        x: "gateways pushing",
        y: "values stored per second",
        series: vec![Series {
            name: "stored",
            points,
        }],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_reach_the_maximum() {
        assert_eq!(
            steps(18_000),
            [1000, 2000, 4000, 6000, 8000, 10_000, 12_000, 14_000, 16_000, 18_000]
        );
        assert_eq!(steps(3000), [1000, 2000, 3000]);
        assert_eq!(steps(500), [500]);
    }
}
