//! `canlift-bench portal --phases curves`: how the portal's costs grow (docs/BENCHMARKS.md
//! §Growth curves). Three sweeps on one portal process — its memory while gateways come
//! online step by step, the reconnect storm's time against the number of gateways (new TLS
//! sessions and resumed ones), values stored per second against the number of pushing
//! gateways — each written as CSV and drawn as SVG into `--curves DIR`. (`canlift-bench
//! gateway --curves DIR` adds the gateway's latency against subscriptions held.)

use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use plotters::prelude::*;

use crate::portal::{fleet_args, ingest, portal_online, storm_once, PortalBench, PortalProcess};
use crate::process::mib;
use gateway::fleet::Fleet;

/// One line of a plot: its name and its points.
pub(super) struct Series {
    pub(super) name: &'static str,
    pub(super) points: Vec<(f64, f64)>,
}

/// A curve: what it shows, its axes, its lines; written as `NAME.csv` and `NAME.svg`.
pub(super) struct Curve {
    pub(super) name: &'static str,
    pub(super) title: &'static str,
    pub(super) x: &'static str,
    pub(super) y: &'static str,
    pub(super) series: Vec<Series>,
}

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

impl Curve {
    /// `NAME.csv` and `NAME.svg` into `out` (made if missing).
    pub(super) fn write(&self, out: &Path) -> anyhow::Result<()> {
        std::fs::create_dir_all(out).with_context(|| out.display().to_string())?;
        let csv = out.join(format!("{}.csv", self.name));
        std::fs::write(&csv, self.csv()).with_context(|| csv.display().to_string())?;
        let svg = out.join(format!("{}.svg", self.name));
        self.draw(&svg)
            .map_err(|e| anyhow::anyhow!("{}: {e}", svg.display()))
    }

    /// `x,series,y` per point: one file for any number of lines.
    fn csv(&self) -> String {
        let mut text = format!("{},series,{}\n", self.x, self.y);
        for series in &self.series {
            for (x, y) in &series.points {
                text.push_str(&format!("{x},{},{y:.3}\n", series.name));
            }
        }
        text
    }

    fn draw(&self, path: &Path) -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::new(path, (720, 420)).into_drawing_area();
        root.fill(&WHITE)?;
        let points = || self.series.iter().flat_map(|s| s.points.iter());
        let x_max = points().map(|p| p.0).fold(0.0, f64::max) * 1.05;
        // Headroom above the highest point for the legend.
        let y_max = points().map(|p| p.1).fold(0.0, f64::max) * 1.25;
        let mut chart = ChartBuilder::on(&root)
            .caption(self.title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(64)
            .build_cartesian_2d(0.0..x_max.max(1.0), 0.0..y_max.max(1.0))?;
        let y_digits = if y_max < 10.0 { 1 } else { 0 };
        chart
            .configure_mesh()
            .light_line_style(WHITE)
            .x_desc(self.x)
            .y_desc(self.y)
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_label_formatter(&|y| format!("{y:.y_digits$}"))
            .draw()?;
        for (i, series) in self.series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(
                    series.points.iter().copied(),
                    color.stroke_width(2),
                ))?
                .label(series.name)
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 16, y)], color.stroke_width(2))
                });
            chart.draw_series(
                series
                    .points
                    .iter()
                    .map(|p| Circle::new(*p, 3, color.filled())),
            )?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
        Ok(())
    }
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

    /// A curve is written as CSV (one line per point) and drawn as an SVG with its title,
    /// axes and legend as text.
    #[test]
    fn a_curve_is_written_and_drawn() {
        let dir = tempfile::tempdir().unwrap();
        let curve = Curve {
            name: "c",
            title: "Cost vs load",
            x: "load",
            y: "cost",
            series: vec![
                Series {
                    name: "a",
                    points: vec![(0.0, 1.0), (10.0, 2.5)],
                },
                Series {
                    name: "b",
                    points: vec![(10.0, 4.0)],
                },
            ],
        };
        curve.write(dir.path()).unwrap();
        let csv = std::fs::read_to_string(dir.path().join("c.csv")).unwrap();
        assert_eq!(csv, "load,series,cost\n0,a,1.000\n10,a,2.500\n10,b,4.000\n");
        let svg = std::fs::read_to_string(dir.path().join("c.svg")).unwrap();
        for text in [
            "<svg",
            "Cost vs load",
            "\nload\n",
            "\ncost\n",
            "\na\n",
            "\nb\n",
            "<circle",
        ] {
            assert!(svg.contains(text), "{text} in {svg}");
        }
    }
}
