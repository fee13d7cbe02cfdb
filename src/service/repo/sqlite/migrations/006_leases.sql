-- 6: leases (the claiming worker, its fencing token, when the lease runs out) and the
-- tenants' turns.
ALTER TABLE jobs ADD COLUMN owner TEXT;
ALTER TABLE jobs ADD COLUMN token INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN lease_until INTEGER;
CREATE TABLE turns (tenant TEXT PRIMARY KEY NOT NULL, served INTEGER NOT NULL);
