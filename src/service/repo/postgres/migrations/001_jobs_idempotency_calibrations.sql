-- 1: jobs, idempotent answers and calibrations, as SQLite's first five versions.
CREATE TABLE jobs (
        id           TEXT PRIMARY KEY NOT NULL,
        status       TEXT NOT NULL,
        stage        TEXT,
        progress     DOUBLE PRECISION NOT NULL DEFAULT 0,
        created_at   BIGINT NOT NULL,
        started_at   BIGINT,
        finished_at  BIGINT,
        heartbeat_at BIGINT,
        attempts     BIGINT NOT NULL DEFAULT 0,
        image_count  BIGINT NOT NULL DEFAULT 0,
        options      TEXT NOT NULL,
        error        TEXT,
        result       TEXT,
        artifacts    TEXT,
        tenant       TEXT NOT NULL DEFAULT 'default',
        callback     TEXT
    );
CREATE INDEX jobs_by_created ON jobs (created_at DESC, id DESC);
CREATE INDEX jobs_by_status ON jobs (status, finished_at);
CREATE INDEX jobs_by_tenant ON jobs (tenant, created_at DESC, id DESC);
CREATE TABLE idempotency (
        tenant     TEXT NOT NULL,
        scope      TEXT NOT NULL,
        key        TEXT NOT NULL,
        body_hash  TEXT NOT NULL,
        status     INTEGER NOT NULL,
        body       TEXT NOT NULL,
        location   TEXT,
        created_at BIGINT NOT NULL,
        PRIMARY KEY (tenant, scope, key)
    );
CREATE INDEX idempotency_by_age ON idempotency (created_at);
CREATE TABLE calibrations (
        id          TEXT PRIMARY KEY NOT NULL,
        tenant      TEXT NOT NULL,
        created_at  BIGINT NOT NULL,
        detail      TEXT NOT NULL,
        light_table TEXT NOT NULL,
        artifacts   TEXT NOT NULL
    );
CREATE INDEX calibrations_by_created ON calibrations (created_at DESC, id DESC);
CREATE INDEX calibrations_by_tenant ON calibrations (tenant, created_at DESC, id DESC);
