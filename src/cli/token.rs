//! `lightmapd token`: create, list and revoke the bearer tokens of a server run with
//! `--auth`, in the database the server uses (docs/service.md).

use std::path::PathBuf;

use clap::{Subcommand, ValueEnum};
use lightmapd::service;

use super::serve::database_url;
use super::{Failure, bad_input, runtime};

#[derive(clap::Args)]
pub(crate) struct TokenArgs {
    #[command(subcommand)]
    action: TokenAction,
    /// The server's data folder (its database is DATA_DIR/lightmapd.db).
    #[arg(long, default_value = "lightmapd-data", global = true)]
    data_dir: PathBuf,
    /// postgres://… or sqlite://FILE, when the server was given --database-url (default:
    /// $LIGHTMAPD_DATABASE_URL, or the contents of $LIGHTMAPD_DATABASE_URL_FILE).
    #[arg(long, global = true)]
    database_url: Option<String>,
}

#[derive(Subcommand)]
enum TokenAction {
    /// Make a token; its secret is printed once, on stdout.
    Create {
        /// A name for people (who or what uses it); unique among live tokens.
        #[arg(long)]
        name: String,
        /// editor: its own scenes and jobs, priority up to --max-priority; admin: every
        /// client's jobs, any priority.
        #[arg(long, value_enum, default_value = "editor")]
        role: RoleArg,
    },
    /// Every token: id, name, role, created, active/revoked, source.
    List,
    /// Revoke a token by id, or by name when one live token has it.
    Revoke { token: String },
    /// Print a fresh random secret for a --tokens-file line (touches no database).
    Secret,
}

#[derive(Clone, Copy, ValueEnum)]
enum RoleArg {
    Editor,
    Admin,
}

pub(crate) fn token(args: TokenArgs) -> Result<(), Failure> {
    if let TokenAction::Secret = args.action {
        println!("{}", service::auth::new_secret());
        return Ok(());
    }
    let config = service::Config {
        data_dir: args.data_dir,
        database_url: database_url(args.database_url)?,
        ..service::Config::default()
    };
    let fail = |e: &dyn std::fmt::Display| Failure {
        code: 1,
        message: format!("token: {e}"),
    };
    runtime()?.block_on(async move {
        let (queue, _) = service::open_backends(&config).await.map_err(|e| fail(&e))?;
        match args.action {
            TokenAction::Create { name, role } => {
                if name.trim().is_empty() || name.chars().any(char::is_whitespace) {
                    return Err(bad_input("--name must be one word (no spaces)"));
                }
                let role = match role {
                    RoleArg::Editor => service::queue::Role::Editor,
                    RoleArg::Admin => service::queue::Role::Admin,
                };
                let (record, secret) = service::auth::create_token(&*queue, &name, role)
                    .await
                    .map_err(|e| token_failure(&e))?;
                eprintln!(
                    "token {} ({name}, {}) created; its secret is shown only now:",
                    record.id,
                    role.as_str()
                );
                println!("{secret}");
            }
            TokenAction::List => {
                for t in queue.tokens().await.map_err(|e| fail(&e))? {
                    let revoked = t
                        .revoked_at
                        .map(|ms| format!("revoked {}", service::model::rfc3339(ms)))
                        .unwrap_or_else(|| "active".into());
                    println!(
                        "{}\t{}\t{}\tcreated {}\t{revoked}\t{}",
                        t.id,
                        t.name,
                        t.role.as_str(),
                        service::model::rfc3339(t.created_at),
                        t.source
                    );
                }
            }
            TokenAction::Revoke { token } => {
                let t = service::auth::resolve_token(&*queue, &token)
                    .await
                    .map_err(|e| token_failure(&e))?;
                if !queue
                    .revoke_token(&t.id, service::queue::now_ms())
                    .await
                    .map_err(|e| fail(&e))?
                {
                    return Err(bad_input(format!("no active token with id or name {token:?}")));
                }
                eprintln!("token {} ({}) revoked", t.id, t.name);
            }
            TokenAction::Secret => {}
        }
        Ok(())
    })
}

fn token_failure(e: &service::auth::TokenError) -> Failure {
    match e {
        service::auth::TokenError::Invalid(m) => bad_input(m.clone()),
        service::auth::TokenError::Database(e) => Failure {
            code: 1,
            message: format!("token: {e}"),
        },
    }
}
