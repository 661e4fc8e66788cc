//! Single sign-on with OpenID Connect (docs/PORTAL.md §Single sign-on): the web UI's
//! authorization code flow (OpenID Connect Core 1.0 §3.1) with PKCE (RFC 7636, S256), the
//! provider found by discovery (OpenID Connect Discovery 1.0 §4), its ID token checked as
//! §3.1.3.7 says — signature by a key of its JWKS (RS256/384/512, PS256/384/512, ES256/384,
//! EdDSA; never `none` or a shared-secret HMAC), issuer, audience, authorized party, expiry,
//! issue time, nonce — and the user's groups mapped to a role.
//!
//! Everything here but [`Sso`]'s fetches is plain functions of their inputs and the time given,
//! tested without a provider; the flow's state (state, nonce, PKCE verifier) lives in the
//! browser's own cookie for the ten minutes a sign-in may take, so any process of a cluster
//! can finish what another began.

use std::time::{Duration, Instant};

use base64::engine::general_purpose::URL_SAFE_NO_PAD as B64URL;
use base64::Engine;
use serde::Deserialize;
use serde_json::{Map, Value};

use cloud_types::users::Role;

use crate::config::OidcSection;
use crate::outbound::{Https, Target};

/// Why a sign-on did not sign anyone in.
#[derive(Debug, thiserror::Error)]
pub enum SsoError {
    /// The provider could not be reached or answered nonsense (logged; the browser is told
    /// the provider is unavailable).
    #[error("the OpenID provider: {0}")]
    Provider(String),
    /// The provider refused (the user cancelled, or the provider's policy).
    #[error("the OpenID provider refused: {0}")]
    Refused(String),
    /// The ID token or the answer failed a check: a forgery, a replay, a mix-up.
    #[error("the ID token: {0}")]
    Token(String),
    /// The ID token names a signing key the provider's key set does not have (yet: it may
    /// have rotated its keys since they were fetched).
    #[error("the ID token: {0}")]
    UnknownKey(String),
}

/// What the provider's discovery document says (Discovery 1.0 §3; the fields used).
#[derive(Debug, Clone, Deserialize)]
pub struct Discovery {
    /// Must be the configured issuer exactly (§4.3).
    pub issuer: String,
    /// Where the browser is sent to sign in.
    pub authorization_endpoint: String,
    /// Where the code is exchanged.
    pub token_endpoint: String,
    /// Where the signing keys are.
    pub jwks_uri: String,
    /// Where the claims are when the ID token does not carry them.
    #[serde(default)]
    pub userinfo_endpoint: Option<String>,
}

/// A JSON Web Key Set (RFC 7517 §5).
#[derive(Debug, Clone, Default, Deserialize)]
pub struct Jwks {
    /// The keys.
    pub keys: Vec<Jwk>,
}

/// One public key (RFC 7517 §4, RFC 7518 §6): what is needed to check a signature.
#[derive(Debug, Clone, Deserialize)]
pub struct Jwk {
    /// `RSA`, `EC` or `OKP`.
    pub kty: String,
    /// The key's id, matched with a token header's `kid`.
    #[serde(default)]
    pub kid: Option<String>,
    /// The one algorithm the key is for, if it says.
    #[serde(default)]
    pub alg: Option<String>,
    /// `sig` or `enc`; an encryption key is never used to check a signature.
    #[serde(default, rename = "use")]
    pub usage: Option<String>,
    /// RSA modulus (base64url).
    #[serde(default)]
    pub n: Option<String>,
    /// RSA exponent (base64url).
    #[serde(default)]
    pub e: Option<String>,
    /// EC or OKP curve.
    #[serde(default)]
    pub crv: Option<String>,
    /// EC x coordinate, or the OKP public key (base64url).
    #[serde(default)]
    pub x: Option<String>,
    /// EC y coordinate (base64url).
    #[serde(default)]
    pub y: Option<String>,
}

/// The flow's state for one browser, kept in its cookie between leaving for the provider and
/// coming back: the `state` the answer must carry, the `nonce` the ID token must carry, and
/// the PKCE verifier only the portal can show the token endpoint.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pending {
    /// Binds the answer to this browser (CSRF).
    pub state: String,
    /// Binds the ID token to this sign-in (replay).
    pub nonce: String,
    /// PKCE (RFC 7636 §4.1).
    pub verifier: String,
}

impl Pending {
    /// 256 random bits each.
    pub fn new() -> Pending {
        let random = || {
            let mut bytes = [0u8; 32];
            rand::Rng::fill(&mut rand::rng(), &mut bytes);
            B64URL.encode(bytes)
        };
        Pending {
            state: random(),
            nonce: random(),
            verifier: random(),
        }
    }

    /// The cookie's value.
    pub fn to_cookie(&self) -> String {
        format!("{}.{}.{}", self.state, self.nonce, self.verifier)
    }

    /// Read back from the cookie; `None` for anything that is not three base64url parts.
    pub fn from_cookie(text: &str) -> Option<Pending> {
        let mut parts = text.split('.');
        let (state, nonce, verifier) = (parts.next()?, parts.next()?, parts.next()?);
        let valid = |p: &str| {
            (43..=128).contains(&p.len())
                && p.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
        };
        (parts.next().is_none() && valid(state) && valid(nonce) && valid(verifier)).then(|| {
            Pending {
                state: state.into(),
                nonce: nonce.into(),
                verifier: verifier.into(),
            }
        })
    }

    /// The PKCE challenge: base64url(SHA-256(verifier)) (RFC 7636 §4.2, S256).
    pub fn challenge(&self) -> String {
        B64URL.encode(ring::digest::digest(
            &ring::digest::SHA256,
            self.verifier.as_bytes(),
        ))
    }
}

impl Default for Pending {
    fn default() -> Self {
        Pending::new()
    }
}

/// The URL the browser is sent to (Core §3.1.2.1).
pub fn authorization_url(
    discovery: &Discovery,
    section: &OidcSection,
    redirect: &str,
    pending: &Pending,
) -> String {
    let mut scopes: Vec<&str> = vec!["openid"];
    scopes.extend(
        section
            .scopes
            .iter()
            .map(String::as_str)
            .filter(|s| *s != "openid"),
    );
    let query = [
        ("response_type", "code"),
        ("client_id", section.client_id.as_str()),
        ("redirect_uri", redirect),
        ("scope", &scopes.join(" ")),
        ("state", &pending.state),
        ("nonce", &pending.nonce),
        ("code_challenge", &pending.challenge()),
        ("code_challenge_method", "S256"),
    ];
    let encoded = serde_urlencoded::to_string(query).unwrap_or_default();
    let joiner = match discovery.authorization_endpoint.contains('?') {
        true => '&',
        false => '?',
    };
    format!("{}{joiner}{encoded}", discovery.authorization_endpoint)
}

/// What an ID token must say to be taken.
#[derive(Debug, Clone, Copy)]
pub struct Expected<'a> {
    /// The configured issuer.
    pub issuer: &'a str,
    /// The portal's client id.
    pub client_id: &'a str,
    /// This sign-in's nonce.
    pub nonce: &'a str,
    /// Now, in seconds since the epoch.
    pub now_s: i64,
}

/// Clocks of the provider and the portal may differ this much.
const SKEW_S: i64 = 120;

/// Check `jwt` against `keys` and `expected` (Core §3.1.3.7); its claims.
pub fn verify_id_token(
    jwt: &str,
    keys: &Jwks,
    expected: &Expected<'_>,
) -> Result<Map<String, Value>, SsoError> {
    let bad = |why: &str| SsoError::Token(why.to_owned());
    let mut parts = jwt.split('.');
    let (Some(header64), Some(payload64), Some(signature64), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(bad("not a signed JWT (three parts)"));
    };
    let decode = |part: &str, what: &str| {
        B64URL
            .decode(part)
            .map_err(|_| SsoError::Token(format!("its {what} is not base64url")))
    };
    let header: Map<String, Value> = serde_json::from_slice(&decode(header64, "header")?)
        .map_err(|_| bad("its header is not a JSON object"))?;
    if header.contains_key("crit") {
        return Err(bad("it names critical extensions"));
    }
    let alg = header
        .get("alg")
        .and_then(Value::as_str)
        .ok_or_else(|| bad("no alg"))?;
    let kid = header.get("kid").and_then(Value::as_str);
    let scheme = Scheme::of(alg).ok_or_else(|| {
        SsoError::Token(format!(
            "alg {alg:?} is not taken (only public-key signatures)"
        ))
    })?;
    let signature = decode(signature64, "signature")?;
    let signed = &jwt[..header64.len() + 1 + payload64.len()];
    let candidates: Vec<&Jwk> = keys
        .keys
        .iter()
        .filter(|k| k.usage.as_deref().is_none_or(|u| u == "sig"))
        .filter(|k| k.alg.as_deref().is_none_or(|a| a == alg))
        .filter(|k| kid.is_none() || k.kid.as_deref() == kid)
        .filter(|k| scheme.fits(k))
        .collect();
    if candidates.is_empty() {
        return Err(SsoError::UnknownKey(format!(
            "no key of the provider's for alg {alg} and kid {kid:?}"
        )));
    }
    if !candidates
        .iter()
        .any(|k| scheme.verify(k, signed.as_bytes(), &signature))
    {
        return Err(bad("the signature does not verify"));
    }
    let claims: Map<String, Value> = serde_json::from_slice(&decode(payload64, "payload")?)
        .map_err(|_| bad("its claims are not a JSON object"))?;
    check_claims(&claims, expected)?;
    Ok(claims)
}

fn check_claims(claims: &Map<String, Value>, expected: &Expected<'_>) -> Result<(), SsoError> {
    let bad = |why: String| Err(SsoError::Token(why));
    let text = |name: &str| claims.get(name).and_then(Value::as_str);
    let number = |name: &str| claims.get(name).and_then(Value::as_i64);
    if text("iss") != Some(expected.issuer) {
        return bad(format!("issuer {:?}, not the configured one", text("iss")));
    }
    let audiences: Vec<&str> = match claims.get("aud") {
        Some(Value::String(a)) => vec![a.as_str()],
        Some(Value::Array(a)) => a.iter().filter_map(Value::as_str).collect(),
        _ => Vec::new(),
    };
    if !audiences.contains(&expected.client_id) {
        return bad("not issued to this portal (aud)".into());
    }
    if audiences.len() > 1 && text("azp") != Some(expected.client_id) {
        return bad("issued to several parties and not authorized for this portal (azp)".into());
    }
    match number("exp") {
        Some(exp) if exp + SKEW_S > expected.now_s => {}
        Some(_) => return bad("expired".into()),
        None => return bad("no expiry (exp)".into()),
    }
    match number("iat") {
        Some(iat) if iat - SKEW_S <= expected.now_s => {}
        Some(_) => return bad("issued in the future (iat)".into()),
        None => return bad("no issue time (iat)".into()),
    }
    if text("nonce") != Some(expected.nonce) {
        return bad("not of this sign-in (nonce)".into());
    }
    if text("sub").is_none_or(str::is_empty) {
        return bad("no subject (sub)".into());
    }
    Ok(())
}

/// The signature schemes taken, by JWS `alg` (RFC 7518 §3.1, RFC 8037 §3.1).
#[derive(Debug, Clone, Copy)]
enum Scheme {
    Rsa(&'static ring::signature::RsaParameters),
    Ec(
        &'static ring::signature::EcdsaVerificationAlgorithm,
        &'static str,
    ),
    Ed25519,
}

impl Scheme {
    fn of(alg: &str) -> Option<Scheme> {
        use ring::signature as s;
        Some(match alg {
            "RS256" => Scheme::Rsa(&s::RSA_PKCS1_2048_8192_SHA256),
            "RS384" => Scheme::Rsa(&s::RSA_PKCS1_2048_8192_SHA384),
            "RS512" => Scheme::Rsa(&s::RSA_PKCS1_2048_8192_SHA512),
            "PS256" => Scheme::Rsa(&s::RSA_PSS_2048_8192_SHA256),
            "PS384" => Scheme::Rsa(&s::RSA_PSS_2048_8192_SHA384),
            "PS512" => Scheme::Rsa(&s::RSA_PSS_2048_8192_SHA512),
            "ES256" => Scheme::Ec(&s::ECDSA_P256_SHA256_FIXED, "P-256"),
            "ES384" => Scheme::Ec(&s::ECDSA_P384_SHA384_FIXED, "P-384"),
            "EdDSA" | "Ed25519" => Scheme::Ed25519,
            _ => return None,
        })
    }

    fn fits(self, key: &Jwk) -> bool {
        match self {
            Scheme::Rsa(_) => key.kty == "RSA",
            Scheme::Ec(_, curve) => key.kty == "EC" && key.crv.as_deref() == Some(curve),
            Scheme::Ed25519 => key.kty == "OKP" && key.crv.as_deref() == Some("Ed25519"),
        }
    }

    fn verify(self, key: &Jwk, message: &[u8], signature: &[u8]) -> bool {
        let part = |p: &Option<String>| p.as_deref().and_then(|t| B64URL.decode(t).ok());
        match self {
            Scheme::Rsa(parameters) => match (part(&key.n), part(&key.e)) {
                (Some(n), Some(e)) => ring::signature::RsaPublicKeyComponents { n, e }
                    .verify(parameters, message, signature)
                    .is_ok(),
                _ => false,
            },
            Scheme::Ec(algorithm, _) => match (part(&key.x), part(&key.y)) {
                (Some(x), Some(y)) => {
                    let point = [&[4u8][..], &x, &y].concat();
                    ring::signature::UnparsedPublicKey::new(algorithm, point)
                        .verify(message, signature)
                        .is_ok()
                }
                _ => false,
            },
            Scheme::Ed25519 => part(&key.x).is_some_and(|x| {
                ring::signature::UnparsedPublicKey::new(&ring::signature::ED25519, x)
                    .verify(message, signature)
                    .is_ok()
            }),
        }
    }
}

/// The value at `path` (dotted: `realm_access.roles`) of `claims`.
fn claim<'a>(claims: &'a Map<String, Value>, path: &str) -> Option<&'a Value> {
    let mut parts = path.split('.');
    let mut value = claims.get(parts.next()?)?;
    for part in parts {
        value = value.as_object()?.get(part)?;
    }
    Some(value)
}

/// The role `claims` give by `section`'s map: the highest of the user's groups' roles; none
/// when no group of the user's is in the map.
pub fn role_of(claims: &Map<String, Value>, section: &OidcSection) -> Option<Role> {
    let groups: Vec<&str> = match claim(claims, &section.roles_claim) {
        Some(Value::String(g)) => vec![g.as_str()],
        Some(Value::Array(g)) => g.iter().filter_map(Value::as_str).collect(),
        _ => Vec::new(),
    };
    groups
        .iter()
        .filter_map(|g| section.role_map.get(*g).copied())
        .max()
}

/// The user's name in the portal: `name_claim`, else `email`, else the subject.
pub fn name_of(claims: &Map<String, Value>, section: &OidcSection) -> String {
    [section.name_claim.as_str(), "email", "sub"]
        .into_iter()
        .find_map(|c| claim(claims, c).and_then(Value::as_str))
        .filter(|n| !n.trim().is_empty())
        .unwrap_or_default()
        .trim()
        .to_owned()
}

/// Someone the provider signed in: who (issuer and subject, which never change for them),
/// what the portal calls them, and the role their groups give.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SignedOn {
    /// `ISSUER SUB`: the user's identity across sign-ins.
    pub subject: String,
    /// Their name in the portal.
    pub name: String,
    /// The role their groups give; none: refused.
    pub role: Option<Role>,
}

/// The provider's documents, fetched once and kept for an hour (keys again at once when a
/// token names one not seen yet: the provider rotated them).
#[derive(Debug, Clone)]
struct Known {
    discovery: Discovery,
    keys: Jwks,
    at: Instant,
}

const KNOWN_FOR: Duration = Duration::from_secs(3600);
/// What a provider's document may weigh.
const DOCUMENT_LIMIT: usize = 256 * 1024;

/// The portal's side of single sign-on: `[oidc]` and the provider's documents.
pub struct Sso {
    /// The configuration.
    pub section: OidcSection,
    https: Https,
    known: tokio::sync::Mutex<Option<Known>>,
}

impl Sso {
    /// Prepared from `section` (nothing is fetched yet: a provider that is down does not stop
    /// the portal). The issuer must be `https://`.
    pub fn new(section: OidcSection) -> Result<Sso, String> {
        let target = Target::parse(&section.issuer).map_err(|e| format!("oidc.issuer: {e}"))?;
        if !target.https {
            return Err("oidc.issuer must be https://".into());
        }
        if section.role_map.is_empty() {
            return Err("oidc.role_map maps no group to a role: nobody could sign in".into());
        }
        let https = Https::new(section.ca_file.as_deref()).map_err(|e| format!("oidc: {e}"))?;
        Ok(Sso {
            section,
            https,
            known: tokio::sync::Mutex::new(None),
        })
    }

    /// Where to send the browser, and the state to keep in its cookie.
    pub async fn begin(&self, redirect: &str) -> Result<(String, Pending), SsoError> {
        let known = self.known(false).await?;
        let pending = Pending::new();
        let url = authorization_url(&known.discovery, &self.section, redirect, &pending);
        Ok((url, pending))
    }

    /// Exchange `code` (with the PKCE verifier), check the ID token and read the claims (from
    /// the ID token, the user info where it lacks the groups or the name).
    pub async fn finish(
        &self,
        code: &str,
        pending: &Pending,
        redirect: &str,
    ) -> Result<SignedOn, SsoError> {
        let known = self.known(false).await?;
        let tokens = self
            .exchange(&known.discovery, code, pending, redirect)
            .await?;
        let id_token = tokens
            .get("id_token")
            .and_then(Value::as_str)
            .ok_or_else(|| SsoError::Provider("the token answer has no id_token".into()))?;
        let now_s = cloud_types::now_ms() / 1000;
        let expected = Expected {
            issuer: &self.section.issuer,
            client_id: &self.section.client_id,
            nonce: &pending.nonce,
            now_s,
        };
        let mut claims = match verify_id_token(id_token, &known.keys, &expected) {
            Ok(claims) => claims,
            // A key not seen yet: the provider rotated its keys.
            Err(SsoError::UnknownKey(_)) => {
                let known = self.known(true).await?;
                verify_id_token(id_token, &known.keys, &expected)?
            }
            Err(e) => return Err(e),
        };
        let lacking = claim(&claims, &self.section.roles_claim).is_none()
            || claim(&claims, &self.section.name_claim).is_none();
        if let (true, Some(endpoint), Some(access)) = (
            lacking,
            known.discovery.userinfo_endpoint.as_deref(),
            tokens.get("access_token").and_then(Value::as_str),
        ) {
            let info = self.user_info(endpoint, access).await?;
            // Core §5.3.2: the user info is of the ID token's subject, or it is not used.
            if info.get("sub") != claims.get("sub") {
                return Err(SsoError::Token(
                    "the user info is of another subject".into(),
                ));
            }
            for (k, v) in info {
                claims.entry(k).or_insert(v);
            }
        }
        let sub = claims
            .get("sub")
            .and_then(Value::as_str)
            .unwrap_or_default();
        Ok(SignedOn {
            subject: format!("{} {sub}", self.section.issuer),
            name: name_of(&claims, &self.section),
            role: role_of(&claims, &self.section),
        })
    }

    async fn known(&self, refresh: bool) -> Result<Known, SsoError> {
        let mut known = self.known.lock().await;
        if let Some(k) = known
            .as_ref()
            .filter(|k| !refresh && k.at.elapsed() < KNOWN_FOR)
        {
            return Ok(k.clone());
        }
        let url = format!(
            "{}/.well-known/openid-configuration",
            self.section.issuer.trim_end_matches('/')
        );
        let discovery: Discovery = serde_json::from_value(self.get(&url, None).await?)
            .map_err(|e| SsoError::Provider(format!("its discovery document: {e}")))?;
        if discovery.issuer != self.section.issuer {
            return Err(SsoError::Provider(format!(
                "its discovery document names issuer {:?}, not the configured one",
                discovery.issuer
            )));
        }
        let keys: Jwks = serde_json::from_value(self.get(&discovery.jwks_uri, None).await?)
            .map_err(|e| SsoError::Provider(format!("its keys: {e}")))?;
        let fresh = Known {
            discovery,
            keys,
            at: Instant::now(),
        };
        *known = Some(fresh.clone());
        Ok(fresh)
    }

    async fn exchange(
        &self,
        discovery: &Discovery,
        code: &str,
        pending: &Pending,
        redirect: &str,
    ) -> Result<Map<String, Value>, SsoError> {
        let mut form = vec![
            ("grant_type", "authorization_code"),
            ("code", code),
            ("redirect_uri", redirect),
            ("code_verifier", pending.verifier.as_str()),
        ];
        // RFC 6749 §2.3.1: the secret as Basic authentication, each part form-encoded first;
        // a public client names itself in the body.
        let basic = match &self.section.client_secret {
            Some(secret) => {
                let part = |t: &str| {
                    percent_encoding::utf8_percent_encode(t, percent_encoding::NON_ALPHANUMERIC)
                        .to_string()
                };
                let pair = format!("{}:{}", part(&self.section.client_id), part(secret));
                Some(format!(
                    "Basic {}",
                    base64::engine::general_purpose::STANDARD.encode(pair)
                ))
            }
            None => {
                form.push(("client_id", self.section.client_id.as_str()));
                None
            }
        };
        let body = serde_urlencoded::to_string(&form).unwrap_or_default();
        let target = self.target(&discovery.token_endpoint)?;
        let mut request = hyper::Request::post(&target.path)
            .header("host", host_header(&target))
            .header("content-type", "application/x-www-form-urlencoded")
            .header("accept", "application/json");
        if let Some(basic) = basic {
            request = request.header("authorization", basic);
        }
        let answer = self.send(&target, request, body).await?;
        let json = answer_json(answer.0, answer.1)?;
        match json {
            Value::Object(map) if answer.0 == 200 => Ok(map),
            Value::Object(map) => Err(SsoError::Refused(describe_error(&map))),
            _ => Err(SsoError::Provider(
                "its token answer is not a JSON object".into(),
            )),
        }
    }

    async fn user_info(
        &self,
        endpoint: &str,
        access: &str,
    ) -> Result<Map<String, Value>, SsoError> {
        match self.get(endpoint, Some(access)).await? {
            Value::Object(map) => Ok(map),
            _ => Err(SsoError::Provider(
                "its user info is not a JSON object".into(),
            )),
        }
    }

    /// GET `url` (with `bearer` if given): its JSON.
    async fn get(&self, url: &str, bearer: Option<&str>) -> Result<Value, SsoError> {
        let target = self.target(url)?;
        let mut request = hyper::Request::get(&target.path)
            .header("host", host_header(&target))
            .header("accept", "application/json");
        if let Some(token) = bearer {
            request = request.header("authorization", format!("Bearer {token}"));
        }
        let (status, body) = self.send(&target, request, String::new()).await?;
        if status != 200 {
            return Err(SsoError::Provider(format!("answered {status}")));
        }
        answer_json(status, body)
    }

    fn target(&self, url: &str) -> Result<Target, SsoError> {
        let target = Target::parse(url).map_err(SsoError::Provider)?;
        if !target.https {
            return Err(SsoError::Provider("an endpoint is not https://".into()));
        }
        Ok(target)
    }

    async fn send(
        &self,
        target: &Target,
        request: axum::http::request::Builder,
        body: String,
    ) -> Result<(u16, Option<hyper::body::Bytes>), SsoError> {
        let request = request
            .header("user-agent", concat!("canlift/", env!("CARGO_PKG_VERSION")))
            .body(http_body_util::Full::new(hyper::body::Bytes::from(body)))
            .map_err(|e| SsoError::Provider(e.to_string()))?;
        let answer = tokio::time::timeout(
            Duration::from_secs(10),
            self.https.send(target, None, request, DOCUMENT_LIMIT),
        )
        .await
        .map_err(|_| SsoError::Provider("no answer within 10 s".into()))?
        .map_err(SsoError::Provider)?;
        Ok((answer.status, answer.body))
    }
}

fn host_header(target: &Target) -> String {
    let host = match target.host.contains(':') {
        true => format!("[{}]", target.host),
        false => target.host.clone(),
    };
    match (target.https, target.port) {
        (true, 443) | (false, 80) => host,
        (_, port) => format!("{host}:{port}"),
    }
}

fn answer_json(status: u16, body: Option<hyper::body::Bytes>) -> Result<Value, SsoError> {
    let body = body.ok_or_else(|| {
        SsoError::Provider(format!(
            "its answer ({status}) is longer than {DOCUMENT_LIMIT} bytes"
        ))
    })?;
    serde_json::from_slice(&body)
        .map_err(|_| SsoError::Provider(format!("its answer ({status}) is not JSON")))
}

/// An OAuth error answer (RFC 6749 §5.2) in words: its code and description.
pub fn describe_error(map: &Map<String, Value>) -> String {
    let code = map.get("error").and_then(Value::as_str).unwrap_or("error");
    match map.get("error_description").and_then(Value::as_str) {
        Some(d) => format!("{code}: {d}"),
        None => code.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ring::signature::{EcdsaKeyPair, Ed25519KeyPair, KeyPair, ECDSA_P256_SHA256_FIXED_SIGNING};

    const ISSUER: &str = "https://id.example";
    const CLIENT: &str = "canlift-portal";
    const NONCE: &str = "n-0S6_WzA2Mj";
    const NOW: i64 = 1_800_000_000;

    fn section() -> OidcSection {
        serde_json::from_value(serde_json::json!({
            "issuer": "https://id.example",
            "client_id": "canlift-portal",
            "account": "acme",
            "role_map": {"lift-engineers": "engineer", "lift-viewers": "viewer", "it": "admin"},
        }))
        .unwrap()
    }

    struct Signer {
        key: EcdsaKeyPair,
        jwks: Jwks,
    }

    fn es256() -> Signer {
        let rng = ring::rand::SystemRandom::new();
        let pkcs8 = EcdsaKeyPair::generate_pkcs8(&ECDSA_P256_SHA256_FIXED_SIGNING, &rng).unwrap();
        let key = EcdsaKeyPair::from_pkcs8(&ECDSA_P256_SHA256_FIXED_SIGNING, pkcs8.as_ref(), &rng)
            .unwrap();
        let point = key.public_key().as_ref();
        let jwks = serde_json::from_value(serde_json::json!({"keys": [{
            "kty": "EC", "crv": "P-256", "kid": "k1", "use": "sig",
            "x": B64URL.encode(&point[1..33]), "y": B64URL.encode(&point[33..65]),
        }]}))
        .unwrap();
        Signer { key, jwks }
    }

    fn claims() -> Value {
        serde_json::json!({
            "iss": ISSUER, "aud": CLIENT, "sub": "248289761001", "nonce": NONCE,
            "iat": NOW - 5, "exp": NOW + 300, "preferred_username": "ann",
            "groups": ["staff", "lift-engineers"],
        })
    }

    fn sign(signer: &Signer, header: Value, claims: &Value) -> String {
        let signed = format!(
            "{}.{}",
            B64URL.encode(header.to_string()),
            B64URL.encode(claims.to_string())
        );
        let rng = ring::rand::SystemRandom::new();
        let signature = signer.key.sign(&rng, signed.as_bytes()).unwrap();
        format!("{signed}.{}", B64URL.encode(signature.as_ref()))
    }

    fn expected() -> Expected<'static> {
        Expected {
            issuer: ISSUER,
            client_id: CLIENT,
            nonce: NONCE,
            now_s: NOW,
        }
    }

    fn header() -> Value {
        serde_json::json!({"alg": "ES256", "kid": "k1", "typ": "JWT"})
    }

    #[test]
    fn a_good_token_is_taken_and_its_groups_give_the_highest_role() {
        let signer = es256();
        let token = sign(&signer, header(), &claims());
        let taken = verify_id_token(&token, &signer.jwks, &expected()).unwrap();
        assert_eq!(role_of(&taken, &section()), Some(Role::Engineer));
        assert_eq!(name_of(&taken, &section()), "ann");
        let mut claims = claims();
        claims["groups"] = serde_json::json!(["lift-viewers", "it"]);
        let taken =
            verify_id_token(&sign(&signer, header(), &claims), &signer.jwks, &expected()).unwrap();
        assert_eq!(role_of(&taken, &section()), Some(Role::Admin));
        claims["groups"] = serde_json::json!("staff");
        let taken =
            verify_id_token(&sign(&signer, header(), &claims), &signer.jwks, &expected()).unwrap();
        assert_eq!(
            role_of(&taken, &section()),
            None,
            "no mapped group: refused"
        );
    }

    #[test]
    fn every_check_refuses_what_it_is_for() {
        let signer = es256();
        let refused = |token: String, why: &str| {
            let e = verify_id_token(&token, &signer.jwks, &expected())
                .expect_err(why)
                .to_string();
            assert!(e.contains(why), "{why}: {e}");
        };
        let with = |name: &str, value: Value| {
            let mut c = claims();
            c[name] = value;
            sign(&signer, header(), &c)
        };
        refused(with("iss", "https://evil.example".into()), "issuer");
        refused(with("aud", "someone-else".into()), "aud");
        refused(with("aud", serde_json::json!([CLIENT, "other"])), "azp");
        refused(with("exp", (NOW - SKEW_S - 1).into()), "expired");
        refused(with("iat", (NOW + SKEW_S + 1).into()), "future");
        refused(with("nonce", "another".into()), "nonce");
        refused(with("sub", "".into()), "subject");
        // Tampered claims, a key of another's, another kid.
        let token = sign(&signer, header(), &claims());
        let mut parts: Vec<&str> = token.split('.').collect();
        let forged = B64URL.encode(with_groups_admin().to_string());
        parts[1] = &forged;
        refused(parts.join("."), "signature");
        let other = es256();
        refused(sign(&other, header(), &claims()), "signature");
        refused(
            sign(
                &signer,
                serde_json::json!({"alg": "ES256", "kid": "k9"}),
                &claims(),
            ),
            "no key",
        );
        // alg confusion: none, an HMAC keyed with public material, an RSA alg for an EC key.
        let unsigned = format!(
            "{}.{}.",
            B64URL.encode(r#"{"alg":"none"}"#),
            B64URL.encode(claims().to_string())
        );
        refused(unsigned, "not taken");
        refused(
            sign(&signer, serde_json::json!({"alg": "HS256"}), &claims()),
            "not taken",
        );
        refused(
            sign(&signer, serde_json::json!({"alg": "RS256"}), &claims()),
            "no key",
        );
        refused(
            sign(
                &signer,
                serde_json::json!({"alg": "ES256", "crit": ["exp"]}),
                &claims(),
            ),
            "critical",
        );
        refused("a.b".into(), "three parts");
    }

    fn with_groups_admin() -> Value {
        let mut c = claims();
        c["groups"] = serde_json::json!(["it"]);
        c
    }

    #[test]
    fn ed25519_tokens_and_a_key_set_without_kids() {
        let rng = ring::rand::SystemRandom::new();
        let pkcs8 = Ed25519KeyPair::generate_pkcs8(&rng).unwrap();
        let key = Ed25519KeyPair::from_pkcs8(pkcs8.as_ref()).unwrap();
        let jwks: Jwks = serde_json::from_value(serde_json::json!({"keys": [
            {"kty": "RSA", "n": "AQAB", "e": "AQAB", "use": "sig"},
            {"kty": "OKP", "crv": "Ed25519", "x": B64URL.encode(key.public_key().as_ref())},
        ]}))
        .unwrap();
        let signed = format!(
            "{}.{}",
            B64URL.encode(r#"{"alg":"EdDSA"}"#),
            B64URL.encode(claims().to_string())
        );
        let token = format!("{signed}.{}", B64URL.encode(key.sign(signed.as_bytes())));
        assert!(verify_id_token(&token, &jwks, &expected()).is_ok());
    }

    #[test]
    fn the_flow_state_goes_through_a_cookie_and_pkce_is_s256() {
        let pending = Pending::new();
        assert_eq!(
            Pending::from_cookie(&pending.to_cookie()),
            Some(pending.clone())
        );
        assert_eq!(Pending::from_cookie("a.b.c"), None);
        assert_eq!(
            Pending::from_cookie(&format!("{}.x", pending.to_cookie())),
            None
        );
        // RFC 7636 Appendix B.
        let rfc = Pending {
            state: String::new(),
            nonce: String::new(),
            verifier: "dBjftJeZ4CVP-mB92K27uhbUJU1p1r_wW1gFWFOEjXk".into(),
        };
        assert_eq!(
            rfc.challenge(),
            "E9Melhoa2OwvFrEMTJguCHaoeK1t8URWbuGJSstw-cM"
        );
        let discovery = Discovery {
            issuer: ISSUER.into(),
            authorization_endpoint: "https://id.example/auth?tenant=7".into(),
            token_endpoint: "https://id.example/token".into(),
            jwks_uri: "https://id.example/jwks".into(),
            userinfo_endpoint: None,
        };
        let url = authorization_url(
            &discovery,
            &section(),
            "https://portal.example/login/sso/callback",
            &pending,
        );
        assert!(
            url.starts_with("https://id.example/auth?tenant=7&response_type=code&"),
            "{url}"
        );
        for part in [
            "scope=openid+profile+email",
            "code_challenge_method=S256",
            "redirect_uri=https%3A%2F%2Fportal.example%2Flogin%2Fsso%2Fcallback",
            &format!("nonce={}", pending.nonce),
            &format!("code_challenge={}", pending.challenge()),
        ] {
            assert!(url.contains(part), "{part} in {url}");
        }
    }

    #[test]
    fn nested_role_claims_and_names() {
        let mut section = section();
        section.roles_claim = "realm_access.roles".into();
        let claims: Map<String, Value> = serde_json::from_value(serde_json::json!({
            "sub": "x", "email": "vic@example.com", "realm_access": {"roles": ["lift-viewers"]},
        }))
        .unwrap();
        assert_eq!(role_of(&claims, &section), Some(Role::Viewer));
        assert_eq!(name_of(&claims, &section), "vic@example.com");
        assert!(Sso::new(OidcSection {
            issuer: "http://id.example".into(),
            ..section.clone()
        })
        .is_err());
        assert!(Sso::new(OidcSection {
            role_map: Default::default(),
            ..section
        })
        .is_err());
    }
}
