//! The portal in a lift company's IT (docs/PORTAL.md §Metrics): `/metrics` as `promtool check
//! metrics` wants it, with histograms that fill as requests come; the gateway's own metrics
//! likewise; the alert rules and the dashboard in contrib/ name only metrics that exist and pass
//! `promtool check rules`.

use std::collections::BTreeSet;

use serde_json::Value;
use testkit::constants::{LIFT, METRICS_TOKEN};
use testkit::portal::Rig;

/// The metric names an expression or a dashboard names: `canlift_…` and `process_…`, without
/// a histogram's `_bucket`, `_sum` and `_count`.
fn names_in(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for (at, _) in text.match_indices(['c', 'p']) {
        let rest = &text[at..];
        if !(rest.starts_with("canlift_") || rest.starts_with("process_")) {
            continue;
        }
        if at > 0 && text.as_bytes()[at - 1].is_ascii_alphanumeric() {
            continue;
        }
        let name: String = rest
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        let name = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|s| name.strip_suffix(s))
            .map_or(name.clone(), str::to_owned);
        names.insert(name);
    }
    names
}

/// The families of an exposition (its `# TYPE` lines).
fn families(text: &str) -> BTreeSet<String> {
    text.lines()
        .filter_map(|l| l.strip_prefix("# TYPE "))
        .filter_map(|l| l.split_whitespace().next())
        .map(str::to_owned)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_pass_promtool_and_contrib_names_only_what_exists() {
    let listen = std::net::SocketAddr::from(([127, 0, 0, 1], testkit::free_port()));
    let rig = Rig::builder()
        .gateway(move |g| g.metrics.listen = Some(listen))
        .start()
        .await;
    rig.online().await;
    // Requests that fill the histograms: operator requests, gateway round trips.
    for _ in 0..3 {
        let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
        assert_eq!(rig.call("GET", &path, Some(&rig.key), None).await.0, 200);
    }
    let (status, portal) = rig.call("GET", "/metrics", Some(METRICS_TOKEN), None).await;
    assert_eq!(status, 200);
    let portal = portal.as_str().unwrap_or_default().to_owned();
    assert!(
        portal.contains("canlift_http_request_duration_seconds_count{method=\"GET\",route=\"/api/v1/lifts/{id}/objects/{mplex}\"} 3"),
        "{portal}"
    );
    assert!(
        portal.contains("canlift_gateway_round_trip_seconds_bucket{method=\"get_canopen_object\"")
    );
    assert!(portal.contains("# TYPE process_open_fds gauge"));
    let gateway = testkit::portal::until(
        testkit::constants::WAIT,
        "the gateway's metrics",
        || async {
            cloud::client::scrape(listen)
                .await
                .is_ok_and(|m| m.0.contains("canlift_gateway_connected 1"))
        },
    )
    .await;
    eprintln!("gateway metrics after {gateway:?}");
    let gateway = cloud::client::scrape(listen)
        .await
        .map(|m| m.0)
        .unwrap_or_default();
    assert!(
        gateway.contains("canlift_gateway_accesses_total{outcome=\"ok\"}"),
        "{gateway}"
    );

    // Every metric contrib/ names exists: the portal's, its cluster's, the gateway's.
    let mut known = families(&portal);
    known.extend(families(&gateway));
    known.extend(cloud::metrics::family_names().map(str::to_owned));
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let rules = std::fs::read_to_string(root.join("contrib/prometheus/canlift.rules.yml")).unwrap();
    let dashboard =
        std::fs::read_to_string(root.join("contrib/grafana/canlift-portal.json")).unwrap();
    let parsed: Value = serde_json::from_str(&dashboard).expect("the dashboard is JSON");
    assert!(parsed["panels"].as_array().is_some_and(|p| p.len() > 10));
    for (file, text) in [("rules", &rules), ("dashboard", &dashboard)] {
        let unknown: Vec<_> = names_in(text).difference(&known).cloned().collect();
        assert!(
            unknown.is_empty(),
            "{file} names metrics that do not exist: {unknown:?}"
        );
    }

    let Some(promtool) = testkit::promtool() else {
        rig.stop().await;
        return;
    };
    for (what, text) in [("portal", &portal), ("gateway", &gateway)] {
        let (ok, said) = testkit::run_promtool(&promtool, &["check", "metrics"], text);
        assert!(ok, "promtool check metrics, {what}: {said}\n{text}");
    }
    let rules_path = root.join("contrib/prometheus/canlift.rules.yml");
    let (ok, said) = testkit::run_promtool(
        &promtool,
        &["check", "rules", rules_path.to_str().unwrap()],
        "",
    );
    assert!(ok, "promtool check rules: {said}");
    rig.stop().await;
}

/// A site that reaches the internet only through an HTTP proxy: the gateway tunnels through
/// tinyproxy (`[cloud] proxy`) with TLS end to end; with the proxy gone it does not get through
/// another way.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_reaches_the_portal_through_a_proxy_and_no_other_way() {
    let Some(mut proxy) = testkit::proxy::Tinyproxy::start(&[]) else {
        return;
    };
    let url = proxy.url();
    let mut rig = Rig::builder()
        .gateway(move |g| g.cloud.proxy = Some(url))
        .start()
        .await;
    rig.online().await;
    let port = rig.url().rsplit(':').next().unwrap_or_default().to_owned();
    let log = proxy.log();
    assert!(
        log.contains("CONNECT") && log.contains(&format!(":{port}")),
        "the proxy tunnelled to the portal: {log}"
    );
    // Read through the tunnel: the gateway answers as ever.
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    assert_eq!(rig.call("GET", &path, Some(&rig.key), None).await.0, 200);
    // No proxy, no way: the gateway does not reach the portal by itself.
    proxy.stop();
    rig.restart_gateway(|_| {}).await;
    tokio::time::sleep(std::time::Duration::from_secs(3)).await;
    let (_, lifts) = rig.call("GET", "/api/v1/lifts", Some(&rig.key), None).await;
    assert_eq!(lifts[0]["online"], false, "{lifts}");
    rig.stop().await;
}
