//! Single sign-on against a real OpenID provider — node-oidc-provider (OpenID Certified, from
//! npm), started by the test over HTTPS with a private CA the portal trusts by `[oidc] ca_file` —
//! in headless Chromium: people sign in through the provider's pages and get the role their
//! directory group maps to, the role follows the groups at the next sign-in, someone in no
//! mapped group is refused, and the portal's own sign-in with an API key still works.

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use fantoccini::{Client, Locator};
use tokio::io::AsyncBufReadExt;

use cloud::config::OidcSection;
use cloud_types::users::Role;
use testkit::constants::ACCOUNT;
use testkit::portal::Rig;

use super::browser::{browser, chromedriver, click, text_of, type_into, until};

const CLIENT_ID: &str = "canlift-portal";
const CLIENT_SECRET: &str = "the-portal's-secret at the provider";

/// The provider process (stopped when dropped) and where its standard error goes.
struct Provider {
    _child: tokio::process::Child,
    log: std::path::PathBuf,
}

/// The provider on `port`, sending browsers back to `redirect`, with the directory in
/// `groups`.
async fn provider(
    dir: &Path,
    port: u16,
    pki: &testkit::pki::TestPki,
    redirect: &str,
    groups: &Path,
) -> Provider {
    let log = groups.with_file_name("provider.log");
    let mut child = tokio::process::Command::new("node")
        .arg(dir.join("provider.mjs"))
        .arg(port.to_string())
        .arg(&pki.cert)
        .arg(&pki.key)
        .args([redirect, CLIENT_ID, CLIENT_SECRET])
        .arg(groups)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("a log file"))
        .kill_on_drop(true)
        .spawn()
        .expect("node starts");
    let mut lines = tokio::io::BufReader::new(child.stdout.take().expect("stdout")).lines();
    let ready = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .expect("the provider starts within 30 s")
        .expect("a line");
    assert!(
        ready.is_some_and(|l| l.starts_with("READY ")),
        "the provider is ready"
    );
    // What else it says is read, so that its writes never meet a closed pipe.
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    Provider { _child: child, log }
}

/// From the sign-in page, through the provider's login and consent pages as `login` (any
/// password does), until the browser is back on the portal: the path it landed on.
async fn sign_on(client: &Client, provider: &Provider, base: &str, login: &str) -> String {
    client
        .goto(&format!("{base}/login"))
        .await
        .expect("the sign-in page");
    let button = text_of(client, "p.sso a.button").await;
    assert_eq!(button.as_deref(), Some("Sign in with Example ID"));
    click(client, "p.sso a.button").await;
    let mut typed = false;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let at = client.current_url().await.expect("a URL");
        let back = at.as_str().starts_with(base)
            && (!at.path().starts_with("/login/sso") || at.path() == "/login/sso/callback");
        if back {
            return at.path().to_owned();
        }
        if tokio::time::Instant::now() > deadline {
            let page = text_of(client, "body").await.unwrap_or_default();
            let log = std::fs::read_to_string(&provider.log).unwrap_or_default();
            panic!("{login} is not back on the portal within 30 s: at {at}, showing {page:?}; the provider said {log:?}");
        }
        if !typed {
            if let Ok(name) = client.find(Locator::Css("input[name=login]")).await {
                name.send_keys(login).await.expect("typed");
                type_into(client, "input[name=password]", "any password").await;
                typed = true;
                click(client, "button[type=submit]").await;
                continue;
            }
        }
        // The consent page asks once per client.
        if let Ok(consent) = client.find(Locator::Css("button[autofocus]")).await {
            let _ = consent.click().await;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Forget every session: the portal's and the provider's (cookies are not kept apart by port).
async fn sign_out_everywhere(client: &Client) {
    client.delete_all_cookies().await.expect("cookies deleted");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn people_sign_in_through_their_company_directory() {
    let Some((chromium, chromedriver_path)) = testkit::browser() else {
        return;
    };
    let Some(provider_dir) = testkit::oidc_provider() else {
        return;
    };
    let scratch = testkit::scratch();
    // The provider's certificate is of a private CA of its own, not the portal's.
    let pki_dir = scratch.path().join("provider-pki");
    std::fs::create_dir_all(&pki_dir).expect("a directory");
    let pki = testkit::pki::pki(&pki_dir);
    let groups = scratch.path().join("groups.json");
    let directory = |ann: &[&str]| {
        let json = serde_json::json!({
            "ann": ann, "vic": ["lift-viewers"], "eve": ["staff"],
        });
        std::fs::write(&groups, json.to_string()).expect("written");
    };
    directory(&["lift-engineers", "staff"]);
    let provider_port = testkit::free_port();
    let issuer = format!("https://localhost:{provider_port}");
    let section = OidcSection {
        issuer: issuer.clone(),
        client_id: CLIENT_ID.into(),
        client_secret: Some(CLIENT_SECRET.into()),
        account: ACCOUNT.into(),
        roles_claim: "groups".into(),
        role_map: [
            ("lift-engineers".to_owned(), Role::Engineer),
            ("lift-viewers".to_owned(), Role::Viewer),
        ]
        .into(),
        name_claim: "preferred_username".into(),
        scopes: ["openid", "profile", "groups"].map(String::from).to_vec(),
        ca_file: Some(pki.ca.clone()),
        redirect_url: None,
        label: "Example ID".into(),
    };
    let rig = Rig::builder()
        .without_lift()
        .portal(move |c| c.oidc = Some(section))
        .start()
        .await;
    let base = rig.url();
    let provider = provider(
        &provider_dir,
        provider_port,
        &pki,
        &format!("{base}/login/sso/callback"),
        &groups,
    )
    .await;
    let driver = chromedriver(&chromedriver_path).await;
    let client = browser(&driver, &chromium, &rig.dir().join("chromium-profile")).await;
    let store = rig.store().await;

    // Ann is in lift-engineers: she is made an engineer of the account at her first sign-in.
    let landed = sign_on(&client, &provider, &base, "ann").await;
    assert_eq!(landed, "/", "on to the fleet");
    let who = until("signed in", 10, || text_of(&client, "span.who")).await;
    assert_eq!(who, "ann · engineer");
    let ann = store.operator(ACCOUNT, "ann").await.unwrap().unwrap();
    assert_eq!(ann.role, Role::Engineer);
    // No secret signs her in: the provider is her way in.
    assert_eq!(store.secret_hash(ACCOUNT, "ann").await.unwrap(), "!sso");

    // Vic is in lift-viewers.
    sign_out_everywhere(&client).await;
    sign_on(&client, &provider, &base, "vic").await;
    let who = until("signed in", 10, || text_of(&client, "span.who")).await;
    assert_eq!(who, "vic · viewer");

    // Eve's groups map to no role: refused, and no user is made.
    sign_out_everywhere(&client).await;
    let landed = sign_on(&client, &provider, &base, "eve").await;
    assert_eq!(landed, "/login/sso/callback");
    let refusal = until("refusal", 10, || text_of(&client, "p.error")).await;
    assert_eq!(
        refusal,
        "None of your groups gives a role on this portal: ask its administrator."
    );
    assert!(store.operator(ACCOUNT, "eve").await.unwrap().is_none());
    assert!(
        text_of(&client, "span.who").await.is_none(),
        "not signed in"
    );

    // Ann moves to lift-viewers in the directory: her next sign-in makes her a viewer.
    directory(&["lift-viewers"]);
    sign_out_everywhere(&client).await;
    sign_on(&client, &provider, &base, "ann").await;
    let who = until("signed in", 10, || text_of(&client, "span.who")).await;
    assert_eq!(who, "ann · viewer");

    // A forged answer (a state this browser did not begin) is refused.
    client
        .goto(&format!(
            "{base}/login/sso/callback?code=stolen&state=forged"
        ))
        .await
        .unwrap();
    let refusal = until("refusal", 10, || text_of(&client, "p.error")).await;
    assert!(
        refusal.starts_with("This sign-on was not begun in this browser"),
        "{refusal}"
    );

    // The portal's own sign-in still works beside it.
    sign_out_everywhere(&client).await;
    client.goto(&format!("{base}/login")).await.unwrap();
    type_into(&client, "input[name=key]", &rig.key).await;
    click(&client, "form.login button").await;
    let who = until("signed in with the key", 10, || {
        text_of(&client, "span.who")
    })
    .await;
    assert!(who.ends_with("administrator"), "{who}");

    let _ = client.close().await;
    rig.stop().await;
}
