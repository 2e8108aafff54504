-- The measurement runs (a database written before migrations were versioned has these
-- tables already: they are kept as they are).
CREATE TABLE IF NOT EXISTS runs(id INTEGER PRIMARY KEY, started REAL NOT NULL, device TEXT NOT NULL, options TEXT NOT NULL,
    status TEXT NOT NULL, seconds REAL NOT NULL DEFAULT 0, heartbeat REAL NOT NULL, result TEXT);
CREATE TABLE IF NOT EXISTS states(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, stage TEXT NOT NULL, u_rms REAL, i_rms REAL,
    gain REAL, f_hp REAL, x_min REAL, x_max REAL, dtv REAL, re REAL, residual REAL);
CREATE TABLE IF NOT EXISTS estimates(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, residual REAL, parameters TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS distortion(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, bl_x REAL, kms_x REAL, le_x REAL,
    bl_i REAL, kms_i REAL, le_i REAL, bl_p REAL, kms_p REAL, le_p REAL, dominant_x TEXT, dominant_p TEXT);
CREATE INDEX IF NOT EXISTS states_run_t ON states(run, t);
