-- The shared (PostgreSQL) queue: the same tables and meaning as migrations/sqlite/ after
-- both of its migrations (scenes, jobs, tokens, the client of each scene and job), in
-- one step since no PostgreSQL deployment predates issue 11. Times are Unix
-- milliseconds, as in SQLite, so both stores hand the same numbers to the API.
--
-- Differences, each on purpose:
-- - JSON columns are JSONB (validated on write; SQLite stores text);
-- - cancel_requested is a BOOLEAN (SQLite: 0/1);
-- - seq stands in for SQLite's rowid as the tie-break between jobs made in the same
--   millisecond (claim order and listing order);
-- - a trigger sends the NOTIFYs that wake idle workers and event streams in other
--   processes (src/service/queue/postgres.rs explains the channels).

CREATE TABLE scenes (
    id           TEXT PRIMARY KEY,
    -- Not unique: with tokens, the same bytes from two clients are two scenes.
    content_hash TEXT NOT NULL,
    -- 'glb' or 'gltf' (multipart: the main .gltf plus its buffers and images)
    format       TEXT NOT NULL,
    main_file    TEXT NOT NULL,
    files        JSONB NOT NULL,   -- array of stored file names
    size_bytes   BIGINT NOT NULL,
    report       JSONB NOT NULL,   -- import report
    created_at   BIGINT NOT NULL,
    client       TEXT
);
CREATE INDEX scenes_content ON scenes (content_hash);

CREATE TABLE jobs (
    id               TEXT PRIMARY KEY,
    seq              BIGINT GENERATED ALWAYS AS IDENTITY,
    scene_id         TEXT NOT NULL,
    spec             JSONB NOT NULL,   -- job body, defaults filled in
    status           TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    priority         INTEGER NOT NULL DEFAULT 0,
    created_at       BIGINT NOT NULL,
    started_at       BIGINT,
    finished_at      BIGINT,
    attempts         INTEGER NOT NULL DEFAULT 0,
    worker           TEXT,
    lease_expires_at BIGINT,
    cancel_requested BOOLEAN NOT NULL DEFAULT FALSE,
    progress         JSONB,
    history          JSONB NOT NULL DEFAULT '[]',
    plan             JSONB,
    snapshots        INTEGER NOT NULL DEFAULT 0,
    summary          JSONB,            -- when succeeded
    failure          TEXT,
    updated_at       BIGINT NOT NULL,
    -- The token id that submitted it, or `ip:ADDR` without authentication.
    client           TEXT
);

-- The claim: queued jobs only, highest priority first, then oldest. Partial, so the
-- index stays as small as the queue however long the history grows.
CREATE INDEX jobs_claim ON jobs (priority DESC, created_at, seq) WHERE status = 'queued';
CREATE INDEX jobs_scene ON jobs (scene_id, status);
CREATE INDEX jobs_lease ON jobs (lease_expires_at) WHERE status = 'running';
CREATE INDEX jobs_client ON jobs (client, status);
CREATE INDEX jobs_listing ON jobs (created_at DESC, seq DESC);

-- Bearer tokens: only the hex SHA-256 of the secret is stored.
CREATE TABLE tokens (
    id         TEXT PRIMARY KEY,
    seq        BIGINT GENERATED ALWAYS AS IDENTITY,
    name       TEXT NOT NULL,
    hash       TEXT NOT NULL UNIQUE,
    created_at BIGINT NOT NULL,
    revoked_at BIGINT
);

-- NOTIFY on commit: `lightmapd_work` (payload: job id) when a job becomes queued, so
-- idle workers anywhere try a claim; `lightmapd_job` (payload: job id) when what an
-- event stream shows changed (status, progress, plan, snapshots, cancel flag), so the
-- API process holding that stream re-reads the row. A heartbeat that only renews the
-- lease changes none of these and sends nothing.
CREATE FUNCTION lightmapd_jobs_notify() RETURNS trigger AS $$
BEGIN
    IF NEW.status = 'queued' AND (TG_OP = 'INSERT' OR OLD.status <> 'queued') THEN
        PERFORM pg_notify('lightmapd_work', NEW.id);
    END IF;
    IF TG_OP = 'INSERT'
        OR NEW.status IS DISTINCT FROM OLD.status
        OR NEW.progress IS DISTINCT FROM OLD.progress
        OR NEW.plan IS DISTINCT FROM OLD.plan
        OR NEW.snapshots IS DISTINCT FROM OLD.snapshots
        OR NEW.cancel_requested IS DISTINCT FROM OLD.cancel_requested THEN
        PERFORM pg_notify('lightmapd_job', NEW.id);
    END IF;
    RETURN NULL;
END;
$$ LANGUAGE plpgsql;

CREATE TRIGGER jobs_notify AFTER INSERT OR UPDATE ON jobs
    FOR EACH ROW EXECUTE FUNCTION lightmapd_jobs_notify();
