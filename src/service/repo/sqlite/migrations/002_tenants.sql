-- 2: jobs belong to tenants; those recorded before belong to the open API's tenant.
ALTER TABLE jobs ADD COLUMN tenant TEXT NOT NULL DEFAULT 'default';
CREATE INDEX jobs_by_tenant ON jobs (tenant, created_at DESC, id DESC);
