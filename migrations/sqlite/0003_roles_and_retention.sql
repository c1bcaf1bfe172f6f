-- Issue 24: token roles, where a token came from, and the index the retention sweeper
-- reads.
--
-- tokens.role: 'editor' (its own scenes and jobs, priority up to --max-priority) or
-- 'admin' (every client's jobs, any priority). Tokens made before roles existed are
-- editors: that is what they could do before.
-- tokens.source: 'cli' (`lightmapd token create`) or 'file' (`serve --tokens-file`, kept
-- in step with the file at every start: a line removed from the file revokes its token).
ALTER TABLE tokens ADD COLUMN role TEXT NOT NULL DEFAULT 'editor' CHECK (role IN ('admin', 'editor'));
ALTER TABLE tokens ADD COLUMN source TEXT NOT NULL DEFAULT 'cli';

-- Finished jobs by age, for the retention sweeper (--job-retention-hours).
CREATE INDEX jobs_finished ON jobs (finished_at) WHERE status IN ('succeeded', 'failed', 'cancelled');
