//! Trend rules (docs/PORTAL.md §Trends): an object's mean over the last `window_h` hours against
//! its mean over the `baseline_h` hours before. A rise beyond `rise_percent` raises a `trend`
//! alarm; falling back clears it. Judged sans-IO ([`judge`]); [`run`] asks the store for the
//! means now and then and hands the verdicts to the alarm service.

use std::time::Duration;

use nxg::mplex::Mplex;
use tokio::sync::mpsc;

use crate::alarms::rules::{Rules, Verdict};
use crate::config::TrendRule;
use cloud_store::Store;

/// A mean and how many values made it.
pub type Mean = (f64, u64);

/// What a rule says of one lift: `Some(true)` the rise is beyond the rule, `Some(false)` it is
/// not, `None` there is nothing to judge (no values in the window or the baseline, or a
/// baseline of zero or below, against which no percentage means anything).
pub fn judge(rule: &TrendRule, baseline: Option<Mean>, window: Option<Mean>) -> Option<bool> {
    let (base, _) = baseline?;
    let (now, _) = window?;
    if base <= 0.0 {
        return None;
    }
    Some(now > base * (1.0 + rule.rise_percent / 100.0))
}

/// How often a rule is judged: a quarter of its window, between 2 s and 5 min.
pub fn period(rule: &TrendRule) -> Duration {
    Duration::from_secs_f64((rule.window_h * 3600.0 / 4.0).clamp(2.0, 300.0))
}

fn hours_ms(h: f64) -> i64 {
    (h * 3_600_000.0).round() as i64
}

/// Judge `rules` on every lift now and then, sending the verdicts to the alarm service until
/// it is gone.
pub async fn run(
    store: Store,
    rules: Vec<(Mplex, TrendRule)>,
    alarms: Rules,
    verdicts: mpsc::Sender<Vec<Verdict>>,
) {
    let Some(every) = rules.iter().map(|(_, r)| period(r)).min() else {
        return;
    };
    let mut ticks = tokio::time::interval(every);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Each rule at its own period: a rule over days is not asked every few seconds because
    // another looks at minutes.
    let mut due = vec![tokio::time::Instant::now(); rules.len()];
    loop {
        let tick = ticks.tick().await;
        let now = cloud_types::now_ms();
        let mut out = Vec::new();
        for ((mplex, rule), due) in rules.iter().zip(&mut due) {
            if *due > tick {
                continue;
            }
            *due = tick + period(rule);
            let object = mplex.to_string();
            let split = now - hours_ms(rule.window_h);
            let start = split - hours_ms(rule.baseline_h);
            let (window, baseline) = match (
                store.means(&object, split, now).await,
                store.means(&object, start, split).await,
            ) {
                (Ok(w), Ok(b)) => (w, b),
                (Err(e), _) | (_, Err(e)) => {
                    tracing::warn!(error = %e, rule = %rule.name, "trend rule not judged");
                    continue;
                }
            };
            for (lift, now) in &window {
                let base = baseline.get(lift).copied();
                match judge(rule, base, Some(*now)) {
                    Some(true) => {
                        let base = base.map_or(0.0, |b| b.0);
                        out.push(alarms.trend(lift, &object, rule, base, now.0));
                    }
                    Some(false) => out.push(alarms.trend_over(lift, &object)),
                    None => {}
                }
            }
        }
        if !out.is_empty() && verdicts.send(out).await.is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule() -> TrendRule {
        TrendRule {
            mplex: "0x440301".into(),
            name: "Door closing time".into(),
            rise_percent: 20.0,
            baseline_h: 24.0,
            window_h: 1.0,
        }
    }

    #[test]
    fn a_rise_beyond_the_percentage_raises_and_falling_back_clears() {
        let r = rule();
        assert_eq!(judge(&r, Some((2000.0, 50)), Some((2401.0, 3))), Some(true));
        assert_eq!(
            judge(&r, Some((2000.0, 50)), Some((2400.0, 3))),
            Some(false)
        );
        assert_eq!(
            judge(&r, Some((2000.0, 50)), Some((1500.0, 3))),
            Some(false)
        );
        assert_eq!(judge(&r, None, Some((2400.0, 3))), None, "no baseline yet");
        assert_eq!(judge(&r, Some((2000.0, 50)), None), None, "nothing recent");
        assert_eq!(judge(&r, Some((0.0, 50)), Some((1.0, 1))), None);
    }

    #[test]
    fn rules_are_judged_four_times_a_window_within_bounds() {
        let mut r = rule();
        assert_eq!(period(&r), Duration::from_secs(300));
        r.window_h = 20.0 / 3600.0;
        assert_eq!(period(&r), Duration::from_secs(5));
        r.window_h = 1.0 / 3600.0;
        assert_eq!(period(&r), Duration::from_secs(2));
    }
}
