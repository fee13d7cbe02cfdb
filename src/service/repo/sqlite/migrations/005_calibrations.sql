-- 5: light calibrations.
CREATE TABLE calibrations (
        id         TEXT PRIMARY KEY NOT NULL,
        tenant     TEXT NOT NULL,
        created_at INTEGER NOT NULL,
        detail     TEXT NOT NULL,
        light_table TEXT NOT NULL,
        artifacts  TEXT NOT NULL
    );
CREATE INDEX calibrations_by_created ON calibrations (created_at DESC, id DESC);
CREATE INDEX calibrations_by_tenant ON calibrations (tenant, created_at DESC, id DESC);
