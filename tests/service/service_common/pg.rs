//! PostgreSQL fixtures of the tests that run `lightmapd` processes on a shared database
//! (`tests/service/scale_out.rs`, `tests/service/real_faults.rs`): a schema per test, child processes
//! killed when a test fails half-way, signals, and an audit trigger on job status.

use std::process::{Child, Command};
use std::time::{Duration, Instant};

use lightmapd::service::queue::postgres::{PostgresQueue, test_url};

/// A test's own schema on the test database.
pub struct Db {
    /// The URL every process gets: the test database with the schema as search_path.
    pub url: String,
    pub schema: String,
    pub queue: PostgresQueue,
    pub pool: sqlx::PgPool,
}

impl Db {
    pub async fn new(test: &str) -> Option<Db> {
        let base = test_url(test)?;
        let schema = format!("test_{}", uuid::Uuid::new_v4().simple());
        // Creates the schema and migrates it before any process starts.
        let queue = PostgresQueue::open_in_schema(&base, &schema)
            .await
            .unwrap_or_else(|e| panic!("{test}: cannot open PostgreSQL at {base}: {e}"));
        let sep = if base.contains('?') { '&' } else { '?' };
        let url = format!("{base}{sep}options=-c%20search_path%3D{schema}");
        let pool = sqlx::postgres::PgPoolOptions::new()
            .max_connections(2)
            .connect(&url)
            .await
            .unwrap();
        Some(Db {
            url,
            schema,
            queue,
            pool,
        })
    }

    /// Drops the schema. A failure here is reported, not fatal: the checks have passed,
    /// and a left-over schema only takes space in a test database.
    pub async fn drop(self) {
        self.pool.close().await;
        if let Err(e) = self.queue.drop_schema(&self.schema).await {
            eprintln!("warning: cannot drop test schema {}: {e}", self.schema);
        }
    }
}

/// Child processes, killed if the test fails half-way.
#[derive(Default)]
pub struct Children(pub Vec<Child>);

impl Drop for Children {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Children {
    pub fn by_pid(&mut self, pid: u32) -> Option<Child> {
        let i = self.0.iter().position(|c| c.id() == pid)?;
        Some(self.0.swap_remove(i))
    }
}

pub fn signal(child: &Child, sig: &str) {
    let ok = Command::new("kill")
        .args([sig, &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill {sig} {}", child.id());
}

/// Waits up to `limit` for a child to exit; its exit status.
pub fn wait_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        assert!(
            start.elapsed() < limit,
            "process {} still running after {limit:?}",
            child.id()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Records every status change of a job, so the test can see what each worker did.
pub const AUDIT: &[&str] = &[
    "CREATE TABLE audit (seq BIGSERIAL PRIMARY KEY, job TEXT NOT NULL, old_status TEXT NOT NULL,
         new_status TEXT NOT NULL, worker TEXT, attempts INTEGER NOT NULL)",
    "CREATE FUNCTION audit_jobs() RETURNS trigger AS $$ BEGIN
         INSERT INTO audit (job, old_status, new_status, worker, attempts)
         VALUES (NEW.id, OLD.status, NEW.status, COALESCE(NEW.worker, OLD.worker), NEW.attempts);
         RETURN NULL;
     END $$ LANGUAGE plpgsql",
    "CREATE TRIGGER audit AFTER UPDATE OF status ON jobs FOR EACH ROW
         WHEN (OLD.status IS DISTINCT FROM NEW.status) EXECUTE FUNCTION audit_jobs()",
];

/// A `worker` process on PostgreSQL `db` and artifact store `store` with a lease of
/// `lease_s` seconds, `env` (the S3 server's credentials) and `extra` arguments.
pub fn spawn_pg_worker(db: &str, store: &str, env: &[(&str, String)], lease_s: &str, extra: &[&str]) -> Child {
    std::process::Command::new(super::bin())
        .args([
            "worker",
            "--database-url",
            db,
            "--lease-seconds",
            lease_s,
            "--store",
            store,
        ])
        .args(extra)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap()
}

/// The process id inside a worker name (`HOST-PID-INSTANCE-N`, `service::worker`).
pub fn worker_pid(worker: &str) -> u32 {
    let parts: Vec<&str> = worker.rsplitn(4, '-').collect();
    parts[2]
        .parse()
        .unwrap_or_else(|_| panic!("no pid in worker name {worker:?}"))
}
