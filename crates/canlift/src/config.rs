//! Daemon configuration: a TOML file, then `CANLIFT_<SECTION>_<KEY>` environment overrides,
//! then command-line flags (docs/ARCHITECTURE.md §Conventions). `--print-config` shows the result with defaults.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};
use serde::de::DeserializeOwned;
use serde::Serialize;

/// Load section `section` of the TOML file at `file` (if any) into `T`, applying environment
/// overrides. Unknown keys in the section are an error, so a typo never goes unnoticed.
pub fn load<T: DeserializeOwned + Serialize + Default>(
    file: Option<&Path>,
    section: &str,
) -> anyhow::Result<T> {
    let mut table = match file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let mut doc: toml::Table =
                toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
            match doc.remove(section) {
                Some(toml::Value::Table(t)) => t,
                Some(_) => bail!("{}: [{section}] must be a table", path.display()),
                None => toml::Table::new(),
            }
        }
        None => toml::Table::new(),
    };
    apply_env(&mut table, section, std::env::vars())?;
    T::deserialize(toml::Value::Table(table))
        .with_context(|| format!("invalid [{section}] configuration"))
}

/// Where a daemon's configuration is: `given` (`--config`, or `CANLIFT_CONFIG`), else the
/// installed one, `/etc/canlift/NAME.toml`, when it exists (the package's place for it).
pub fn or_installed(given: Option<PathBuf>, name: &str) -> Option<PathBuf> {
    given.or_else(|| {
        let installed = Path::new("/etc/canlift").join(format!("{name}.toml"));
        installed.is_file().then_some(installed)
    })
}

/// Load a whole multi-section document (a daemon with several sections, like the gateway) into
/// `T`, applying environment overrides to each of `sections`. A file that does not fit `T` is
/// refused with `FILE:LINE: reason`.
pub fn load_document<T: DeserializeOwned>(
    file: Option<&Path>,
    sections: &[&str],
) -> anyhow::Result<T> {
    let text = match file {
        Some(path) => Some(
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?,
        ),
        None => None,
    };
    let source = file.zip(text.as_deref());
    let mut doc: toml::Table = match source {
        Some((path, text)) => toml::from_str(text).map_err(|e| anyhow!(located(path, text, &e)))?,
        None => toml::Table::new(),
    };
    for section in sections {
        let entry = doc
            .entry(section.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        let toml::Value::Table(table) = entry else {
            bail!("[{section}] must be a table");
        };
        apply_env(table, section, std::env::vars())?;
    }
    T::deserialize(toml::Value::Table(doc)).map_err(|e| {
        // The file's own error has a place; else an environment override is at fault.
        match source.and_then(|(path, text)| {
            let own = toml::from_str::<T>(text).err()?;
            Some(located(path, text, &own))
        }) {
            Some(message) => anyhow!(message),
            None => anyhow!(e).context("invalid configuration (environment overrides)"),
        }
    })
}

/// A TOML error as `FILE:LINE: reason`.
fn located(path: &Path, text: &str, e: &toml::de::Error) -> String {
    let line = e.span().map_or(0, |span| {
        text[..span.start.min(text.len())].matches('\n').count() + 1
    });
    format!("{}:{line}: {}", path.display(), e.message())
}

/// Apply `CANLIFT_<SECTION>_<KEY>=VALUE` overrides. A value is read as TOML (numbers, booleans,
/// arrays) and, failing that, as a plain string.
fn apply_env(
    table: &mut toml::Table,
    section: &str,
    vars: impl Iterator<Item = (String, String)>,
) -> anyhow::Result<()> {
    let prefix = format!("CANLIFT_{}_", section.to_ascii_uppercase());
    for (name, value) in vars {
        let Some(key) = name.strip_prefix(&prefix) else {
            continue;
        };
        let key = key.to_ascii_lowercase();
        let parsed = toml::from_str::<toml::Table>(&format!("v = {value}"))
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or(toml::Value::String(value));
        table.insert(key, parsed);
    }
    Ok(())
}

/// The effective configuration as TOML under `[section]`.
pub fn render<T: Serialize>(section: &str, config: &T) -> anyhow::Result<String> {
    let mut doc = toml::Table::new();
    doc.insert(section.to_owned(), toml::Value::try_from(config)?);
    Ok(toml::to_string_pretty(&doc)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Default, Serialize, Deserialize, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Sample {
        listen: String,
        bitrate: Option<u32>,
        verbose: bool,
    }

    #[test]
    fn env_overrides_file_values() {
        let mut table: toml::Table = toml::from_str("listen = \"a:1\"\nbitrate = 5").unwrap();
        let vars = [
            ("CANLIFT_HUB_BITRATE".to_owned(), "250000".to_owned()),
            ("CANLIFT_HUB_LISTEN".to_owned(), "127.0.0.1:2".to_owned()),
            ("CANLIFT_GATEWAY_BITRATE".to_owned(), "1".to_owned()),
            ("OTHER".to_owned(), "x".to_owned()),
        ];
        apply_env(&mut table, "hub", vars.into_iter()).unwrap();
        let s = Sample::deserialize(toml::Value::Table(table)).unwrap();
        assert_eq!(
            s,
            Sample {
                listen: "127.0.0.1:2".into(),
                bitrate: Some(250_000),
                verbose: false
            }
        );
        let text = render("hub", &s).unwrap();
        assert!(
            text.contains("[hub]") && text.contains("bitrate = 250000"),
            "{text}"
        );
    }

    #[test]
    fn unknown_keys_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(&path, "[hub]\nbitrat = 5\n").unwrap();
        let err = load::<Sample>(Some(&path), "hub").unwrap_err();
        assert!(format!("{err:#}").contains("bitrat"), "{err:#}");
    }

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Document {
        #[serde(default)]
        hub: Option<Sample>,
    }

    #[test]
    fn document_errors_name_the_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.toml");
        std::fs::write(&path, "[hub]\nlisten = \"a:1\"\n").unwrap();
        let doc = load_document::<Document>(Some(&path), &["hub"]).unwrap();
        assert_eq!(doc.hub.map(|h| h.listen).as_deref(), Some("a:1"));
        std::fs::write(&path, "[hub]\nlisten = \"a:1\"\n\nbitrat = 5\n").unwrap();
        let err = load_document::<Document>(Some(&path), &["hub"]).unwrap_err();
        let at = format!("{}:4: unknown field `bitrat`", path.display());
        assert!(format!("{err:#}").starts_with(&at), "{err:#}");
        std::fs::write(&path, "[hub]\nlisten = \"a:1\n").unwrap();
        let err = load_document::<Document>(Some(&path), &["hub"]).unwrap_err();
        let at = format!("{}:2: ", path.display());
        assert!(format!("{err:#}").starts_with(&at), "{err:#}");
    }
}
