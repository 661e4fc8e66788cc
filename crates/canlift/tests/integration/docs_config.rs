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

/// The files of the repository a reader is sent from: the docs, the README, the sources, the
/// contributed configuration (not the build output or downloaded packages).
fn readable_files(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if path.is_dir() {
            if !matches!(
                name.as_str(),
                "target" | "node_modules" | ".git" | ".venv" | "fuzz"
            ) {
                readable_files(&path, out);
            }
        } else if [".rs", ".md", ".toml", ".service", ".yml"]
            .iter()
            .any(|ext| name.ends_with(ext))
        {
            out.push(path);
        }
    }
}

/// A heading or a reference as compared: lower case, without code quotes.
fn normal(text: &str) -> String {
    text.replace('`', "").to_lowercase()
}

/// Every `docs/FILE.md §Section` (and `README §Section`) in the docs and the sources names a
/// heading of that file: a section that was renamed cannot leave a reader at nothing.
#[test]
fn every_section_reference_names_a_heading() {
    let root = testkit::workspace();
    let mut headings: std::collections::HashMap<String, Vec<String>> = Default::default();
    let mut docs: Vec<std::path::PathBuf> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.push(root.join("README.md"));
    for doc in &docs {
        let text = std::fs::read_to_string(doc).unwrap();
        let name = doc.file_name().unwrap().to_string_lossy().into_owned();
        headings.insert(
            name,
            text.lines()
                .filter(|l| l.starts_with('#'))
                .map(|l| normal(l.trim_start_matches('#').trim()))
                .collect(),
        );
    }
    let mut files = Vec::new();
    for dir in ["docs", "crates", "contrib", "scripts", "tests"] {
        readable_files(&root.join(dir), &mut files);
    }
    files.push(root.join("README.md"));
    let mut dangling = Vec::new();
    for file in files {
        let Ok(text) = std::fs::read_to_string(&file) else {
            continue;
        };
        // A reference may run on in the next line of a comment.
        let text: String = text
            .lines()
            .map(|l| {
                l.trim_start()
                    .trim_start_matches("//!")
                    .trim_start_matches("///")
            })
            .map(|l| l.trim_start_matches("//").trim_start_matches('#').trim())
            .collect::<Vec<_>>()
            .join(" ");
        for (at, _) in text.match_indices('§') {
            let before = text[..at].trim_end();
            let target = before
                .rsplit(|c: char| c.is_whitespace() || "([".contains(c))
                .next()
                .unwrap_or_default();
            let target = target.rsplit('/').next().unwrap_or_default();
            let target = if target == "README" {
                "README.md"
            } else {
                target
            };
            let Some(known) = headings.get(target) else {
                continue;
            };
            let rest = &text[at + '§'.len_utf8()..];
            let rest: String = rest.chars().take(90).collect();
            let words = rest
                .split(['(', ')', ',', '.', ';', ':', '"'])
                .next()
                .unwrap_or("");
            let (rest, words) = (normal(&rest), normal(words.trim()));
            if !words.starts_with(|c: char| c.is_alphabetic()) {
                continue;
            }
            if !known
                .iter()
                .any(|h| rest.starts_with(h.as_str()) || h.starts_with(&words))
            {
                let file = file
                    .strip_prefix(&root)
                    .unwrap_or(&file)
                    .display()
                    .to_string();
                dangling.push(format!("{file}: {target} §{words}"));
            }
        }
    }
    assert!(
        dangling.is_empty(),
        "references to no heading:\n{}",
        dangling.join("\n")
    );
}
