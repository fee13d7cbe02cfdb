-- 3: answers to requests with an Idempotency-Key.
CREATE TABLE idempotency (
        tenant     TEXT NOT NULL,
        scope      TEXT NOT NULL,
        key        TEXT NOT NULL,
        body_hash  TEXT NOT NULL,
        status     INTEGER NOT NULL,
        body       TEXT NOT NULL,
        location   TEXT,
        created_at INTEGER NOT NULL,
        PRIMARY KEY (tenant, scope, key)
    );
CREATE INDEX idempotency_by_age ON idempotency (created_at);
