//! `canlift gateway` from the command line: the README's configuration parses, environment
//! variables override it, and a configuration that cannot work is refused with its reason.

use crate::common;
use common::canlift;

fn readme_gateway_config() -> String {
    let readme = std::fs::read_to_string(testkit::workspace().join("README.md")).unwrap();
    let section = readme
        .split("## The elevator gateway")
        .nth(1)
        .expect("README has the gateway section");
    let block = section.split("```toml\n").nth(1).expect("a toml block");
    block.split("```").next().unwrap().to_owned()
}

#[tokio::test]
async fn the_readme_configuration_is_what_the_gateway_reads() {
    let dir = testkit::scratch();
    let path = dir.path().join("gateway.toml");
    std::fs::write(&path, readme_gateway_config()).unwrap();
    let out = canlift()
        .args(["gateway", "--print-config", "--config"])
        .arg(&path)
        .env("CANLIFT_BUS_NODE_ID", "10")
        .output()
        .await
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("sernum = \"180917010200000102\""), "{text}");
    assert!(
        text.contains("node_id = 10"),
        "environment override: {text}"
    );
    assert!(text.contains("max_in_flight = 16"), "{text}");
    assert!(
        text.contains("[policy]")
            && text.contains("index = \"0x1017\"")
            && text.contains("node = 12"),
        "the write policy: {text}"
    );
    // An example whose allow a deny covers would teach a rule that never takes effect.
    let config: gateway::config::Config = toml::from_str(&text).expect("the printed config");
    assert_eq!(config.policy.ineffective(), Vec::<String>::new());
}

#[tokio::test]
async fn refuses_what_cannot_work() {
    let dir = testkit::scratch();
    let path = dir.path().join("gateway.toml");
    for (config, reason) in [
        ("[identity]\nsernum = \"1\"\n[cloud]\nurl = \"ws://127.0.0.1:1/ws\"\n", "TLS only"),
        ("[cloud]\nurl = \"wss://127.0.0.1:1/ws\"\n", "sernum"),
        ("[identity]\nsernum = \"1\"\n[cloud]\nurl = \"wss://x/ws\"\n[privileges]\nsetup_sha1 = \"abc\"\n", "SHA-1"),
        ("[identity]\nsernum = \"1\"\ncolour = \"red\"\n", "colour"),
    ] {
        std::fs::write(&path, config).unwrap();
        let out = canlift()
            .args(["gateway", "--config"])
            .arg(&path)
            .output()
            .await
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{config}");
        assert!(err.contains(reason), "{config}: {err}");
    }
}
