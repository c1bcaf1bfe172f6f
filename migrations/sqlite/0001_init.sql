-- Scenes and jobs for the embedded (SQLite) queue. Times are Unix milliseconds.
-- JSON columns hold what the API returns as is (import report, progress, history,
-- plan, summary) so a new field needs no migration.

CREATE TABLE scenes (
    id           TEXT PRIMARY KEY,
    content_hash TEXT NOT NULL UNIQUE,
    -- 'glb' or 'gltf' (multipart: the main .gltf plus its buffers and images)
    format       TEXT NOT NULL,
    main_file    TEXT NOT NULL,
    files        TEXT NOT NULL,   -- JSON array of stored file names
    size_bytes   INTEGER NOT NULL,
    report       TEXT NOT NULL,   -- JSON import report
    created_at   INTEGER NOT NULL
);

CREATE TABLE jobs (
    id               TEXT PRIMARY KEY,
    scene_id         TEXT NOT NULL,
    spec             TEXT NOT NULL,   -- JSON job body, defaults filled in
    status           TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    priority         INTEGER NOT NULL DEFAULT 0,
    created_at       INTEGER NOT NULL,
    started_at       INTEGER,
    finished_at      INTEGER,
    attempts         INTEGER NOT NULL DEFAULT 0,
    worker           TEXT,
    lease_expires_at INTEGER,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    progress         TEXT,            -- JSON
    history          TEXT NOT NULL DEFAULT '[]',
    plan             TEXT,            -- JSON
    snapshots        INTEGER NOT NULL DEFAULT 0,
    summary          TEXT,            -- JSON, when succeeded
    failure          TEXT,
    updated_at       INTEGER NOT NULL
);

-- The claim query: highest priority first, then oldest.
CREATE INDEX jobs_claim ON jobs (status, priority DESC, created_at);
CREATE INDEX jobs_scene ON jobs (scene_id, status);
CREATE INDEX jobs_lease ON jobs (status, lease_expires_at);
