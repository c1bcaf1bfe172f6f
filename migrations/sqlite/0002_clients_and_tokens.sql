-- Bearer tokens (issue 12) and the client each scene and job belongs to.
--
-- tokens.hash is the hex SHA-256 of the token; the token itself is shown once, at
-- creation, and never stored. jobs.client / scenes.client hold the id of the token that
-- made them (`tok_…`) when authentication is on, or `ip:ADDR` for jobs made without it
-- (used for the per-client queue limit only; such rows belong to no token).

CREATE TABLE tokens (
    id         TEXT PRIMARY KEY,
    name       TEXT NOT NULL,
    hash       TEXT NOT NULL UNIQUE,
    created_at INTEGER NOT NULL,
    revoked_at INTEGER
);

ALTER TABLE jobs ADD COLUMN client TEXT;
CREATE INDEX jobs_client ON jobs (client, status);

-- With tokens, the same bytes uploaded by two clients are two scenes (neither may learn
-- that the other has it), so content_hash is no longer unique: SQLite cannot drop a
-- constraint, hence the rebuild.
CREATE TABLE scenes_new (
    id           TEXT PRIMARY KEY,
    content_hash TEXT NOT NULL,
    format       TEXT NOT NULL,
    main_file    TEXT NOT NULL,
    files        TEXT NOT NULL,
    size_bytes   INTEGER NOT NULL,
    report       TEXT NOT NULL,
    created_at   INTEGER NOT NULL,
    client       TEXT
);
INSERT INTO scenes_new (id, content_hash, format, main_file, files, size_bytes, report, created_at)
    SELECT id, content_hash, format, main_file, files, size_bytes, report, created_at FROM scenes;
DROP TABLE scenes;
ALTER TABLE scenes_new RENAME TO scenes;
CREATE INDEX scenes_content ON scenes (content_hash);
