//! Curves the benchmarks draw (docs/BENCHMARKS.md §Growth curves): written as CSV and drawn
//! as SVG (no fonts, no bitmaps).

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

/// One line of a plot: its name and its points.
pub(crate) struct Series {
    pub(crate) name: &'static str,
    pub(crate) points: Vec<(f64, f64)>,
}

/// A curve: what it shows, its axes, its lines; written as `NAME.csv` and `NAME.svg`.
pub(crate) struct Curve {
    pub(crate) name: &'static str,
    pub(crate) title: &'static str,
    pub(crate) x: &'static str,
    pub(crate) y: &'static str,
    pub(crate) series: Vec<Series>,
}

impl Curve {
    /// `NAME.csv` and `NAME.svg` into `out` (made if missing).
    pub(crate) fn write(&self, out: &Path) -> anyhow::Result<()> {
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
