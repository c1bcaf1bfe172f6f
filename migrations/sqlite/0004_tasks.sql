-- Issue 25: one job baked as several tasks by several workers, what workers can run,
-- and which workers a job no longer gives its tasks to.
--
-- jobs.tasks: how many bake tasks the job is split into; 0 = not split (claimed whole,
-- as before). A split job is never claimed whole: its `tasks` rows are.
-- jobs.requires_gpu / requires_oidn: the job's `requires` (also in its spec), as columns
-- so the claim filters on them.
ALTER TABLE jobs ADD COLUMN tasks INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN requires_gpu INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN requires_oidn INTEGER NOT NULL DEFAULT 0;
-- jobs.memory_bytes: the job's estimated peak memory (`worker::job_memory`, computed at
-- submission); a worker whose per-job limit is below it does not claim it. 0 for jobs
-- queued before this column.
ALTER TABLE jobs ADD COLUMN memory_bytes INTEGER NOT NULL DEFAULT 0;

-- One row per task: idx 0 .. count-1 bake a range of the job's steps; idx = count is
-- the merge, 'waiting' until every bake task has succeeded. Each task has its own
-- lease and attempts (a dead worker's task is taken up again, not the job).
CREATE TABLE tasks (
    job_id           TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    idx              INTEGER NOT NULL,
    count            INTEGER NOT NULL,
    status           TEXT NOT NULL CHECK (status IN ('waiting', 'queued', 'running', 'succeeded', 'failed', 'cancelled')),
    attempts         INTEGER NOT NULL DEFAULT 0,
    worker           TEXT,
    lease_expires_at INTEGER,
    steps            INTEGER NOT NULL DEFAULT 0,   -- steps baked so far by this attempt
    seconds          REAL NOT NULL DEFAULT 0,      -- its bake time so far
    error            REAL,                         -- its own relative error estimate
    failure          TEXT,
    started_at       INTEGER,
    finished_at      INTEGER,
    updated_at       INTEGER NOT NULL,
    PRIMARY KEY (job_id, idx)
);
CREATE INDEX tasks_claim ON tasks (status, job_id);
CREATE INDEX tasks_lease ON tasks (status, lease_expires_at);

-- Failed or abandoned attempts per (job, worker): a worker with BLOCKLIST_AFTER of them
-- takes no more of that job's tasks (Flamenco's blocklist).
CREATE TABLE task_failures (
    job_id      TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    worker      TEXT NOT NULL,
    failures    INTEGER NOT NULL,
    last_reason TEXT,
    updated_at  INTEGER NOT NULL,
    PRIMARY KEY (job_id, worker)
);

-- Every worker's capabilities (JSON: adapter, kind, gpu, oidn, memory) and when it was
-- last seen alive: the claim gets them as arguments; the API reads this table to say
-- what a job that nobody takes is waiting for.
CREATE TABLE workers (
    id           TEXT PRIMARY KEY,
    capabilities TEXT NOT NULL,
    started_at   INTEGER NOT NULL,
    last_seen    INTEGER NOT NULL
);
CREATE INDEX workers_seen ON workers (last_seen);
