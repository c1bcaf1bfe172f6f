-- Issue 25: one job baked as several tasks by several workers, what workers can run,
-- and which workers a job no longer gives its tasks to (the same as
-- migrations/sqlite/0004_tasks.sql; booleans and JSONB as in 0001).
ALTER TABLE jobs ADD COLUMN tasks INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN requires_gpu BOOLEAN NOT NULL DEFAULT FALSE;
ALTER TABLE jobs ADD COLUMN requires_oidn BOOLEAN NOT NULL DEFAULT FALSE;
ALTER TABLE jobs ADD COLUMN memory_bytes BIGINT NOT NULL DEFAULT 0;

CREATE TABLE tasks (
    job_id           TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    idx              INTEGER NOT NULL,
    count            INTEGER NOT NULL,
    status           TEXT NOT NULL CHECK (status IN ('waiting', 'queued', 'running', 'succeeded', 'failed', 'cancelled')),
    attempts         INTEGER NOT NULL DEFAULT 0,
    worker           TEXT,
    lease_expires_at BIGINT,
    steps            BIGINT NOT NULL DEFAULT 0,
    seconds          DOUBLE PRECISION NOT NULL DEFAULT 0,
    error            REAL,
    failure          TEXT,
    started_at       BIGINT,
    finished_at      BIGINT,
    updated_at       BIGINT NOT NULL,
    PRIMARY KEY (job_id, idx)
);
CREATE INDEX tasks_claim ON tasks (job_id, idx) WHERE status = 'queued';
CREATE INDEX tasks_lease ON tasks (lease_expires_at) WHERE status = 'running';

CREATE TABLE task_failures (
    job_id      TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    worker      TEXT NOT NULL,
    failures    INTEGER NOT NULL,
    last_reason TEXT,
    updated_at  BIGINT NOT NULL,
    PRIMARY KEY (job_id, worker)
);

CREATE TABLE workers (
    id           TEXT PRIMARY KEY,
    capabilities JSONB NOT NULL,
    started_at   BIGINT NOT NULL,
    last_seen    BIGINT NOT NULL
);
CREATE INDEX workers_seen ON workers (last_seen);

-- A task that becomes queued (a split job's merge once its bakes are in, a dead
-- worker's task) wakes idle workers anywhere, as a queued job does.
CREATE FUNCTION lightmapd_tasks_notify() RETURNS trigger AS $$
BEGIN
    IF NEW.status = 'queued' AND (TG_OP = 'INSERT' OR OLD.status <> 'queued') THEN
        PERFORM pg_notify('lightmapd_work', NEW.job_id);
    END IF;
    RETURN NULL;
END;
$$ LANGUAGE plpgsql;

CREATE TRIGGER tasks_notify AFTER INSERT OR UPDATE ON tasks
    FOR EACH ROW EXECUTE FUNCTION lightmapd_tasks_notify();
