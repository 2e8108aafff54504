-- Who writes a run (to tell a killed writer), and the units a production station tests.
ALTER TABLE runs ADD COLUMN host TEXT;
ALTER TABLE runs ADD COLUMN pid INTEGER;
CREATE TABLE units(run INTEGER NOT NULL REFERENCES runs(id), seq INTEGER NOT NULL, unit_id TEXT NOT NULL, tested REAL NOT NULL,
    pass INTEGER NOT NULL, parameters TEXT NOT NULL, verdict TEXT NOT NULL, PRIMARY KEY(run, seq));
CREATE INDEX units_unit ON units(unit_id, tested);
