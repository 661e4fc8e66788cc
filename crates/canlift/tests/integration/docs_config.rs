//! The configuration references cannot go stale: every key a daemon prints with
//! `--print-config` must appear in its documentation.

use std::process::Command;

fn keys(command: &str) -> Vec<String> {
    let out = Command::new(env!("CARGO_BIN_EXE_canlift"))
        .args([command, "--print-config"])
        .env_remove("CANLIFT_STATE_DIR")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: toml::Table = toml::from_str(&String::from_utf8_lossy(&out.stdout)).unwrap();
    let mut keys = Vec::new();
    for (section, value) in doc {
        match value {
            toml::Value::Table(t) => keys.extend(t.keys().map(|k| format!("{section}.{k}"))),
            _ => keys.push(section),
        }
    }
    keys
}

fn read(path: &str) -> String {
    std::fs::read_to_string(testkit::workspace().join(path)).unwrap()
}

fn documented(keys: &[String], doc: &str, what: &str) {
    for key in keys {
        let name = key.rsplit('.').next().unwrap_or(key);
        let found = doc.contains(&format!("{name} ="))
            || doc.contains(&format!("`{name}`"))
            || doc.contains(&format!("[[{name}]]"));
        assert!(found, "{what}: {key} is not documented");
    }
}

#[test]
fn every_daemon_key_is_documented() {
    let readme = read("README.md");
    documented(&keys("hub"), &readme, "README (hub)");
    documented(&keys("gateway"), &readme, "README (gateway)");
    documented(&keys("cloud"), &read("docs/PORTAL.md"), "docs/PORTAL.md");
}
