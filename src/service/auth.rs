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
//! Limits: no scopes or expiry; a revoked token stops working at its next request.

use std::net::SocketAddr;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use crate::service::AppState;
use crate::service::problem::Problem;
use crate::service::queue::{Queue, TokenRecord, now_ms};

/// Who is calling.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Caller {
    /// The token id when tokens are required; else `None`.
    pub token: Option<String>,
    /// What the per-client queue limit counts by: the token id, or `ip:ADDR`.
    pub client: String,
}

impl Caller {
    /// Whether this caller may see a row made by `owner` (anyone may without tokens).
    pub fn owns(&self, owner: Option<&str>) -> bool {
        match &self.token {
            None => true,
            Some(t) => owner == Some(t.as_str()),
        }
    }
}

/// Hex SHA-256 of a token secret, as stored.
pub fn hash_secret(secret: &str) -> String {
    Sha256::digest(secret.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Makes and stores a token; returns its record and the secret (shown once).
pub async fn create_token(queue: &dyn Queue, name: &str) -> Result<(TokenRecord, String), sqlx::Error> {
    let secret = format!("lmd_{}{}", uuid::Uuid::new_v4().simple(), uuid::Uuid::new_v4().simple());
    let record = TokenRecord {
        id: format!("tok_{}", &uuid::Uuid::new_v4().simple().to_string()[..12]),
        name: name.to_string(),
        hash: hash_secret(&secret),
        created_at: now_ms(),
        revoked_at: None,
    };
    queue.insert_token(&record).await?;
    Ok((record, secret))
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
        };
        assert!(open.owns(Some("tok_a")) && open.owns(None));
        let a = Caller {
            token: Some("tok_a".into()),
            client: "tok_a".into(),
        };
        assert!(a.owns(Some("tok_a")));
        assert!(!a.owns(Some("tok_b")) && !a.owns(None));
    }
}
