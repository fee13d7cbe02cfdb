-- 4: jobs' webhooks.
ALTER TABLE jobs ADD COLUMN callback TEXT;
