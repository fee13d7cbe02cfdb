-- 2: leases (the claiming worker, its fencing token, when the lease runs out in the
-- database's clock) and the tenants' turns.
ALTER TABLE jobs ADD COLUMN owner TEXT;
ALTER TABLE jobs ADD COLUMN token BIGINT NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN lease_until TIMESTAMPTZ;
CREATE INDEX jobs_by_lease ON jobs (lease_until) WHERE status = 'running';
CREATE TABLE turns (tenant TEXT PRIMARY KEY NOT NULL, served BIGINT NOT NULL);
CREATE SEQUENCE turn_seq;
