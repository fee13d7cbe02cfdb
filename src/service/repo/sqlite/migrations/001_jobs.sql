-- 1: the jobs table.
CREATE TABLE jobs (
        id           TEXT PRIMARY KEY NOT NULL,
        status       TEXT NOT NULL,
        stage        TEXT,
        progress     REAL NOT NULL DEFAULT 0,
        created_at   INTEGER NOT NULL,
        started_at   INTEGER,
        finished_at  INTEGER,
        heartbeat_at INTEGER,
        attempts     INTEGER NOT NULL DEFAULT 0,
        image_count  INTEGER NOT NULL DEFAULT 0,
        options      TEXT NOT NULL,
        error        TEXT,
        result       TEXT,
        artifacts    TEXT
    );
CREATE INDEX jobs_by_created ON jobs (created_at DESC, id DESC);
CREATE INDEX jobs_by_status ON jobs (status, finished_at);
