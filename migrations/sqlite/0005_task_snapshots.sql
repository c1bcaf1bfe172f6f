-- Issue 25: a split job's snapshots while its tasks run. One task at a time claims the
-- next snapshot's number (`snapshot_claims`) once `snapshot_claimed_at` is a snapshot
-- interval old; `snapshots` counts the stored ones, as for a whole job (the same as
-- migrations/postgres/0004_task_snapshots.sql).
ALTER TABLE jobs ADD COLUMN snapshot_claims INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN snapshot_claimed_at INTEGER;
