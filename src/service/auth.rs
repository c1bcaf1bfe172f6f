//! Optional bearer tokens (issue 12): who is calling, and whether they may.
//!
//! How: `lightmapd token create` makes a secret (`lmd_` and 64 hex digits from the OS's
//! random source, through UUID v4) and stores only its SHA-256 with a name and an id
//! (`tok_…`); the secret is printed once. With `serve --auth`, every request but
//! `GET /healthz` and `GET /` (the dashboard page: static HTML holding no data) must carry
//! `Authorization: Bearer SECRET`; the middleware hashes it,
//! looks the hash up (revoked tokens do not match) and hands the route a [`Caller`].
//! Scenes and jobs record the token id that made them, and a caller asking for another
//! token's scene or job is answered 404, exactly as for one that does not exist, so ids
//! cannot be probed. Without `--auth` the caller is identified by its IP address, which
//! only feeds the per-client queue limit.
//!
//! Why SHA-256 and not a password hash: the secrets are 256 random bits, not chosen by
//! people, so there is nothing to slow a guesser down for; a fast hash keeps the lookup
//! one indexed query per request.
//!
//! The dashboard asks for a token when the API answers 401, keeps it in the tab's
//! `sessionStorage` (gone when the tab closes) and sends it as the header on every fetch,
//! previews and downloads included, so the secret never appears in a URL or a log.
//!
//! Roles (issue 24): an `editor` token sees only its own scenes and jobs and may give a
//! job a priority up to `--max-priority`; an `admin` token sees, cancels and deletes every
//! client's jobs and scenes and may set any priority. Without `--auth` every caller is an
//! editor under the priority cap (there is no one to trust more), and owns everything.
//!
//! Tokens from a secret ([`sync_tokens_file`]): `serve --tokens-file FILE` (or
//! `LIGHTMAPD_TOKENS_FILE`) reads `NAME ROLE SECRET` lines at start-up, so a Kubernetes
//! Secret or a compose secret can hold them; a line's token is added if its hash is not
//! live yet, and a token that came from the file but is no longer in it is revoked, so a
//! rotation is: add the new line, roll out, move clients over, remove the old line, roll
//! out again.
//!
//! Limits: no expiry; a revoked token stops working at its next request; a tokens file is
//! read at start-up only.

use std::net::SocketAddr;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use crate::service::AppState;
use crate::service::problem::Problem;
use crate::service::queue::{Queue, Role, TokenRecord, now_ms};

/// Who is calling.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Caller {
    /// The token id when tokens are required; else `None`.
    pub token: Option<String>,
    /// What the per-client queue limit counts by: the token id, or `ip:ADDR`.
    pub client: String,
    /// An admin token: every client's rows, any priority.
    pub admin: bool,
}

impl Caller {
    /// Whether this caller may see a row made by `owner` (anyone may without tokens; an
    /// admin token may see every row).
    pub fn owns(&self, owner: Option<&str>) -> bool {
        match &self.token {
            None => true,
            Some(_) if self.admin => true,
            Some(t) => owner == Some(t.as_str()),
        }
    }

    /// The owner a listing is limited to: this token's id, or `None` (every row) for an
    /// admin token or without tokens.
    pub fn scope(&self) -> Option<&str> {
        if self.admin { None } else { self.token.as_deref() }
    }
}

/// Hex SHA-256 of a token secret, as stored.
pub fn hash_secret(secret: &str) -> String {
    Sha256::digest(secret.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A fresh secret: `lmd_` and 64 hex digits (256 bits from the OS's random source).
pub fn new_secret() -> String {
    format!("lmd_{}{}", uuid::Uuid::new_v4().simple(), uuid::Uuid::new_v4().simple())
}

fn new_id() -> String {
    format!("tok_{}", &uuid::Uuid::new_v4().simple().to_string()[..12])
}

/// Why a token could not be made.
#[derive(Debug)]
pub enum TokenError {
    /// Bad input (the CLI's exit code 2): a name in use, a malformed tokens file.
    Invalid(String),
    Database(sqlx::Error),
}

impl std::fmt::Display for TokenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TokenError::Invalid(m) => f.write_str(m),
            TokenError::Database(e) => write!(f, "{e}"),
        }
    }
}

impl From<sqlx::Error> for TokenError {
    fn from(e: sqlx::Error) -> Self {
        TokenError::Database(e)
    }
}

/// Makes and stores a token; returns its record and the secret (shown once). Names are
/// unique among live tokens, so `token revoke NAME` always means one token.
pub async fn create_token(queue: &dyn Queue, name: &str, role: Role) -> Result<(TokenRecord, String), TokenError> {
    if let Some(t) = queue
        .tokens()
        .await?
        .into_iter()
        .find(|t| t.revoked_at.is_none() && t.name == name)
    {
        return Err(TokenError::Invalid(format!(
            "a live token is already named {name:?} ({}); pick another name, or revoke that one first",
            t.id
        )));
    }
    let secret = new_secret();
    let record = TokenRecord {
        id: new_id(),
        name: name.to_string(),
        hash: hash_secret(&secret),
        created_at: now_ms(),
        revoked_at: None,
        role,
        source: "cli".into(),
    };
    queue.insert_token(&record).await?;
    Ok((record, secret))
}

/// The one live token `id_or_name` means: an id, or the name of exactly one live token.
/// A name several live tokens share (made before names were unique) is refused with
/// their ids.
pub async fn resolve_token(queue: &dyn Queue, id_or_name: &str) -> Result<TokenRecord, TokenError> {
    let live: Vec<TokenRecord> = queue
        .tokens()
        .await?
        .into_iter()
        .filter(|t| t.revoked_at.is_none())
        .collect();
    if let Some(t) = live.iter().find(|t| t.id == id_or_name) {
        return Ok(t.clone());
    }
    let named: Vec<&TokenRecord> = live.iter().filter(|t| t.name == id_or_name).collect();
    match named.as_slice() {
        [one] => Ok((*one).clone()),
        [] => Err(TokenError::Invalid(format!(
            "no active token with id or name {id_or_name:?}"
        ))),
        many => Err(TokenError::Invalid(format!(
            "{} active tokens are named {id_or_name:?} ({}): revoke one by its id",
            many.len(),
            many.iter().map(|t| t.id.as_str()).collect::<Vec<_>>().join(", ")
        ))),
    }
}

/// One line of a tokens file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileToken {
    pub name: String,
    pub role: Role,
    pub secret: String,
}

/// The shortest secret a tokens file may hold (bytes): 128 bits as hex.
pub const MIN_FILE_SECRET: usize = 32;

/// Parses a tokens file: `NAME ROLE SECRET` per line (whitespace between), `#` comments
/// and blank lines ignored. Errors name the line.
pub fn parse_tokens_file(text: &str) -> Result<Vec<FileToken>, String> {
    let mut out: Vec<FileToken> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let n = i + 1;
        let parts: Vec<&str> = line.split_whitespace().collect();
        let [name, role, secret] = parts.as_slice() else {
            return Err(format!(
                "line {n}: expected `NAME ROLE SECRET` (3 fields), got {}",
                parts.len()
            ));
        };
        let role = Role::parse(role).ok_or_else(|| format!("line {n}: role {role:?}: use admin or editor"))?;
        if secret.len() < MIN_FILE_SECRET {
            return Err(format!(
                "line {n} ({name}): the secret is {} characters, fewer than {MIN_FILE_SECRET}: make one with `lightmapd token secret`",
                secret.len()
            ));
        }
        if out.iter().any(|t| t.name == *name) {
            return Err(format!("line {n}: the name {name:?} is given twice"));
        }
        if out.iter().any(|t| t.secret == *secret) {
            return Err(format!("line {n} ({name}): the same secret is given twice"));
        }
        out.push(FileToken {
            name: name.to_string(),
            role,
            secret: secret.to_string(),
        });
    }
    Ok(out)
}

/// What [`sync_tokens_file`] changed.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TokenSync {
    pub added: Vec<String>,
    pub revoked: Vec<String>,
    pub kept: Vec<String>,
}

/// Brings the file-made tokens in step with `wanted`: each line whose secret has no live
/// token with the same name and role gets one; file-made tokens not in `wanted` (or
/// whose name or role changed) are revoked. Tokens made with `token create` are left
/// alone.
pub async fn sync_tokens_file(queue: &dyn Queue, wanted: &[FileToken]) -> Result<TokenSync, sqlx::Error> {
    let now = now_ms();
    let live: Vec<TokenRecord> = queue
        .tokens()
        .await?
        .into_iter()
        .filter(|t| t.revoked_at.is_none())
        .collect();
    let mut sync = TokenSync::default();
    for t in live.iter().filter(|t| t.source == "file") {
        let still = wanted
            .iter()
            .any(|w| hash_secret(&w.secret) == t.hash && w.name == t.name && w.role == t.role);
        if still {
            sync.kept.push(t.name.clone());
        } else {
            queue.revoke_token(&t.id, now).await?;
            sync.revoked.push(t.name.clone());
        }
    }
    for w in wanted {
        let hash = hash_secret(&w.secret);
        if live
            .iter()
            .any(|t| t.hash == hash && t.source == "file" && t.name == w.name && t.role == w.role)
        {
            continue;
        }
        if let Some(t) = live.iter().find(|t| t.hash == hash && t.source != "file") {
            // Hashes are unique: a `token create` secret pasted into the file stays that token.
            tracing::warn!(token = %t.id, name = %w.name, "a tokens-file secret is already a token made with `token create`; left as it is");
            continue;
        }
        // Hashes are unique, revoked rows included: a secret whose token was revoked
        // (a line removed, then put back) is refused below rather than revived.
        let record = TokenRecord {
            id: new_id(),
            name: w.name.clone(),
            hash,
            created_at: now,
            revoked_at: None,
            role: w.role,
            source: "file".into(),
        };
        match queue.insert_token(&record).await {
            Ok(()) => sync.added.push(w.name.clone()),
            Err(sqlx::Error::Database(e)) if e.is_unique_violation() => {
                tracing::error!(name = %w.name, "this tokens-file secret belongs to a revoked token and is not used again: make a new one with `lightmapd token secret`");
            }
            Err(e) => return Err(e),
        }
    }
    Ok(sync)
}

fn unauthorized(detail: &str) -> Response {
    let mut resp = Problem::new(StatusCode::UNAUTHORIZED, "unauthorized", detail).into_response();
    resp.headers_mut().insert(
        header::WWW_AUTHENTICATE,
        HeaderValue::from_static("Bearer realm=\"lightmapd\""),
    );
    resp
}

/// The middleware: puts a [`Caller`] into every request, or answers 401.
pub async fn authenticate(State(state): State<AppState>, mut req: Request, next: Next) -> Response {
    let ip = req
        .extensions()
        .get::<ConnectInfo<SocketAddr>>()
        .map(|c| c.0.ip().to_string())
        .unwrap_or_else(|| "unknown".into());
    if !state.config.auth {
        req.extensions_mut().insert(Caller {
            token: None,
            client: format!("ip:{ip}"),
            admin: false,
        });
        return next.run(req).await;
    }
    if req.method() == axum::http::Method::GET && matches!(req.uri().path(), "/healthz" | "/") {
        return next.run(req).await;
    }
    let Some(value) = req.headers().get(header::AUTHORIZATION) else {
        return unauthorized("this server requires a bearer token: send `Authorization: Bearer TOKEN`");
    };
    let secret = value
        .to_str()
        .ok()
        .and_then(|v| v.strip_prefix("Bearer ").or_else(|| v.strip_prefix("bearer ")))
        .map(str::trim)
        .unwrap_or("");
    if secret.is_empty() {
        return unauthorized("the Authorization header must be `Bearer TOKEN`");
    }
    match state.queue.token_by_hash(&hash_secret(secret)).await {
        Ok(Some(t)) => {
            req.extensions_mut().insert(Caller {
                token: Some(t.id.clone()),
                client: t.id,
                admin: t.role == Role::Admin,
            });
            next.run(req).await
        }
        Ok(None) => unauthorized("unknown or revoked token"),
        Err(e) => Problem::from(e).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn secrets_hash_to_sha256_hex() {
        // SHA-256("abc") from FIPS 180-2, appendix B.1.
        assert_eq!(
            hash_secret("abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn ownership_applies_only_with_tokens() {
        let open = Caller {
            token: None,
            client: "ip:127.0.0.1".into(),
            admin: false,
        };
        assert!(open.owns(Some("tok_a")) && open.owns(None));
        assert_eq!(open.scope(), None);
        let a = Caller {
            token: Some("tok_a".into()),
            client: "tok_a".into(),
            admin: false,
        };
        assert!(a.owns(Some("tok_a")));
        assert!(!a.owns(Some("tok_b")) && !a.owns(None));
        assert_eq!(a.scope(), Some("tok_a"));
        let admin = Caller {
            token: Some("tok_z".into()),
            client: "tok_z".into(),
            admin: true,
        };
        assert!(admin.owns(Some("tok_a")) && admin.owns(None));
        assert_eq!(admin.scope(), None);
    }

    #[test]
    fn tokens_files_parse_and_name_their_bad_lines() {
        let secret = "a".repeat(40);
        let text = format!("# comment\n\nci editor {secret}\n  ops   admin  lmd_{secret}\n");
        assert_eq!(
            parse_tokens_file(&text).unwrap(),
            vec![
                FileToken {
                    name: "ci".into(),
                    role: Role::Editor,
                    secret: secret.clone()
                },
                FileToken {
                    name: "ops".into(),
                    role: Role::Admin,
                    secret: format!("lmd_{secret}")
                },
            ]
        );
        for (text, says) in [
            (
                "ci editor\n".to_string(),
                "line 1: expected `NAME ROLE SECRET` (3 fields), got 2",
            ),
            (
                format!("ci boss {secret}\n"),
                "line 1: role \"boss\": use admin or editor",
            ),
            (
                "ci editor short\n".to_string(),
                "line 1 (ci): the secret is 5 characters, fewer than 32",
            ),
            (
                format!("a editor {secret}\na admin b{secret}\n"),
                "line 2: the name \"a\" is given twice",
            ),
            (
                format!("a editor {secret}\nb admin {secret}\n"),
                "line 2 (b): the same secret is given twice",
            ),
        ] {
            let e = parse_tokens_file(&text).unwrap_err();
            assert!(e.starts_with(says), "{text:?}: {e}");
        }
    }
}
