-- Issue 24: token roles, where a token came from, and the index the retention sweeper
-- reads (the same as migrations/sqlite/0003_roles_and_retention.sql).
--
-- tokens.role: 'editor' (its own scenes and jobs, priority up to --max-priority) or
-- 'admin' (every client's jobs, any priority); older tokens are editors.
-- tokens.source: 'cli' (`lightmapd token create`) or 'file' (`serve --tokens-file`).
ALTER TABLE tokens ADD COLUMN role TEXT NOT NULL DEFAULT 'editor' CHECK (role IN ('admin', 'editor'));
ALTER TABLE tokens ADD COLUMN source TEXT NOT NULL DEFAULT 'cli';

CREATE INDEX jobs_finished ON jobs (finished_at) WHERE status IN ('succeeded', 'failed', 'cancelled');
