//! One connection to either backend, the migrations, and the few statement kinds the tables
//! need (statements are written once, with `$1, $2, ...` placeholders, for both dialects).

use std::path::{Path, PathBuf};

mod sqlite_migrations {
    refinery::embed_migrations!("migrations/sqlite");
}

#[cfg(feature = "postgres")]
mod postgres_migrations {
    refinery::embed_migrations!("migrations/postgres");
}

/// Where the database is.
#[derive(Clone, Debug, PartialEq)]
pub enum Target {
    /// A SQLite file.
    Sqlite(PathBuf),
    /// A PostgreSQL connection URL (`postgres://user:password@host:port/database`).
    Postgres(String),
}

impl Target {
    /// A `postgres://` or `postgresql://` URL, else a SQLite file (a directory: its
    /// `run.sqlite`, where `coilscope measure` writes).
    pub fn parse(spec: &str) -> Target {
        if spec.starts_with("postgres://") || spec.starts_with("postgresql://") {
            Target::Postgres(spec.to_string())
        } else {
            let p = Path::new(spec);
            Target::Sqlite(if p.is_dir() { p.join("run.sqlite") } else { p.to_path_buf() })
        }
    }

    /// The target for messages: the file, or the URL without its password.
    pub fn name(&self) -> String {
        match self {
            Target::Sqlite(p) => p.display().to_string(),
            Target::Postgres(url) => match (url.find("://"), url.rfind('@')) {
                (Some(s), Some(at)) if at > s => {
                    let user = &url[s + 3..at];
                    match user.find(':') {
                        Some(c) => format!("{}{}:***{}", &url[..s + 3], &user[..c], &url[at..]),
                        None => url.clone(),
                    }
                }
                _ => url.clone(),
            },
        }
    }
}

/// A statement's argument.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Arg<'a> {
    F(f64),
    I(i64),
    T(&'a str),
    OptT(Option<&'a str>),
    B(bool),
}

/// A value read back.
#[derive(Clone, Debug)]
pub(crate) enum Cell {
    Null,
    F(f64),
    I(i64),
    T(String),
    /// A boolean column as PostgreSQL returns it (SQLite returns integers).
    #[cfg_attr(not(feature = "postgres"), allow(dead_code))]
    B(bool),
}

impl Cell {
    /// A number (NULL as NaN: a value not known yet when the row was written).
    pub(crate) fn f(&self) -> f64 {
        match self {
            Cell::F(v) => *v,
            Cell::I(v) => *v as f64,
            _ => f64::NAN,
        }
    }

    pub(crate) fn i(&self) -> i64 {
        match self {
            Cell::I(v) => *v,
            Cell::F(v) => *v as i64,
            Cell::B(b) => *b as i64,
            _ => 0,
        }
    }

    pub(crate) fn b(&self) -> bool {
        match self {
            Cell::B(b) => *b,
            Cell::I(v) => *v != 0,
            _ => false,
        }
    }

    pub(crate) fn opt_t(&self) -> Option<String> {
        match self {
            Cell::T(s) => Some(s.clone()),
            _ => None,
        }
    }

    pub(crate) fn t(&self) -> String {
        self.opt_t().unwrap_or_default()
    }
}

enum Conn {
    Sqlite(rusqlite::Connection),
    #[cfg(feature = "postgres")]
    Postgres(postgres::Client),
}

/// An open database, migrated to the current schema.
pub struct Db {
    conn: Conn,
    name: String,
}

/// The key of the advisory lock every PostgreSQL process takes while it migrates, so that
/// stations starting at once apply each migration once.
#[cfg(feature = "postgres")]
const MIGRATION_LOCK: i64 = 0x636f_696c_0000_0000;

impl Db {
    /// Open (or create) the database and bring its schema up to date.
    pub fn open(target: &Target) -> Result<Db, String> {
        let name = target.name();
        match target {
            Target::Sqlite(path) => {
                let mut conn = rusqlite::Connection::open(path)
                    .map_err(|e| format!("{name}: cannot open the run database: {e}"))?;
                conn.execute_batch(
                    "PRAGMA journal_mode = WAL; PRAGMA synchronous = NORMAL; PRAGMA busy_timeout = 10000;",
                )
                .map_err(|e| format!("{name}: not a coilscope run database, or damaged: {e}"))?;
                sqlite_migrations::migrations::runner()
                    .run(&mut conn)
                    .map_err(|e| format!("{name}: not a coilscope run database, or damaged (its schema cannot be brought up to date: {e})"))?;
                Ok(Db { conn: Conn::Sqlite(conn), name })
            }
            #[cfg(feature = "postgres")]
            Target::Postgres(url) => {
                let mut client = postgres::Client::connect(url, postgres::NoTls).map_err(|e| {
                    format!("{name}: cannot connect to the PostgreSQL server ({e}): is it running, and does the URL name its host, port, user and database?")
                })?;
                let err = |e: postgres::Error| format!("{name}: cannot migrate the schema: {e}");
                client.execute("SELECT pg_advisory_lock($1)", &[&MIGRATION_LOCK]).map_err(err)?;
                let done = postgres_migrations::migrations::runner().run(&mut client).map_err(|e| {
                    format!("{name}: not a coilscope run database, or damaged (its schema cannot be brought up to date: {e})")
                });
                client.execute("SELECT pg_advisory_unlock($1)", &[&MIGRATION_LOCK]).map_err(err)?;
                done?;
                Ok(Db { conn: Conn::Postgres(client), name })
            }
            #[cfg(not(feature = "postgres"))]
            Target::Postgres(_) => Err(format!(
                "{name}: this coilscope was built without PostgreSQL (feature `postgres`); give a SQLite file instead"
            )),
        }
    }

    /// Open a database that must exist already (a reader: a missing SQLite file is a
    /// mistyped path, not a new database).
    pub fn open_existing(target: &Target) -> Result<Db, String> {
        if let Target::Sqlite(p) = target {
            if !p.exists() {
                return Err(format!(
                    "{}: no such run database (coilscope measure writes DIR/run.sqlite; a fleet's is a postgres:// URL)",
                    p.display()
                ));
            }
        }
        Db::open(target)
    }

    /// The target's name for messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    pub(crate) fn is_postgres(&self) -> bool {
        !matches!(self.conn, Conn::Sqlite(_))
    }

    /// Run a statement; the rows it changed.
    pub(crate) fn exec(&mut self, sql: &str, args: &[Arg]) -> Result<u64, String> {
        match &mut self.conn {
            Conn::Sqlite(c) => {
                let sql = sqlite_sql(sql);
                let mut st = c.prepare_cached(&sql).map_err(|e| e.to_string())?;
                st.execute(rusqlite::params_from_iter(args.iter().map(sqlite_arg)))
                    .map(|n| n as u64)
                    .map_err(|e| e.to_string())
            }
            #[cfg(feature = "postgres")]
            Conn::Postgres(c) => {
                let owned = pg_args(args);
                let refs: Vec<&(dyn postgres::types::ToSql + Sync)> = owned.iter().map(|b| b.as_ref()).collect();
                c.execute(sql, &refs).map_err(|e| e.to_string())
            }
        }
    }

    /// Run a query; its rows.
    pub(crate) fn query(&mut self, sql: &str, args: &[Arg]) -> Result<Vec<Vec<Cell>>, String> {
        match &mut self.conn {
            Conn::Sqlite(c) => {
                let sql = sqlite_sql(sql);
                let mut st = c.prepare_cached(&sql).map_err(|e| e.to_string())?;
                let n = st.column_count();
                let rows = st
                    .query_map(rusqlite::params_from_iter(args.iter().map(sqlite_arg)), |r| {
                        (0..n)
                            .map(|k| {
                                use rusqlite::types::ValueRef;
                                Ok(match r.get_ref(k)? {
                                    ValueRef::Null => Cell::Null,
                                    ValueRef::Integer(v) => Cell::I(v),
                                    ValueRef::Real(v) => Cell::F(v),
                                    ValueRef::Text(t) => Cell::T(String::from_utf8_lossy(t).into_owned()),
                                    ValueRef::Blob(_) => Cell::Null,
                                })
                            })
                            .collect::<rusqlite::Result<Vec<Cell>>>()
                    })
                    .map_err(|e| e.to_string())?;
                rows.collect::<Result<Vec<_>, _>>().map_err(|e| e.to_string())
            }
            #[cfg(feature = "postgres")]
            Conn::Postgres(c) => {
                use postgres::types::Type;
                let owned = pg_args(args);
                let refs: Vec<&(dyn postgres::types::ToSql + Sync)> = owned.iter().map(|b| b.as_ref()).collect();
                let rows = c.query(sql, &refs).map_err(|e| e.to_string())?;
                rows.iter()
                    .map(|r| {
                        (0..r.len())
                            .map(|k| {
                                let ty = r.columns()[k].type_().clone();
                                let cell = if ty == Type::FLOAT8 {
                                    r.try_get::<_, Option<f64>>(k)?.map_or(Cell::Null, Cell::F)
                                } else if ty == Type::INT8 {
                                    r.try_get::<_, Option<i64>>(k)?.map_or(Cell::Null, Cell::I)
                                } else if ty == Type::INT4 {
                                    r.try_get::<_, Option<i32>>(k)?.map_or(Cell::Null, |v| Cell::I(v as i64))
                                } else if ty == Type::BOOL {
                                    r.try_get::<_, Option<bool>>(k)?.map_or(Cell::Null, Cell::B)
                                } else if ty == Type::TEXT || ty == Type::VARCHAR {
                                    r.try_get::<_, Option<String>>(k)?.map_or(Cell::Null, Cell::T)
                                } else {
                                    Cell::Null
                                };
                                Ok(cell)
                            })
                            .collect::<Result<Vec<Cell>, postgres::Error>>()
                    })
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| e.to_string())
            }
        }
    }

    /// Run `f` in one transaction: all of its writes or none. On SQLite the write lock is taken
    /// at the start (`BEGIN IMMEDIATE`), so that a busy database is waited for there, not
    /// half-way.
    pub(crate) fn transaction<T>(&mut self, f: impl FnOnce(&mut Db) -> Result<T, String>) -> Result<T, String> {
        let begin = if self.is_postgres() { "BEGIN" } else { "BEGIN IMMEDIATE" };
        self.batch(begin)?;
        match f(self) {
            Ok(v) => {
                self.batch("COMMIT")?;
                Ok(v)
            }
            Err(e) => {
                let _ = self.batch("ROLLBACK");
                Err(e)
            }
        }
    }

    fn batch(&mut self, sql: &str) -> Result<(), String> {
        match &mut self.conn {
            Conn::Sqlite(c) => c.execute_batch(sql).map_err(|e| e.to_string()),
            #[cfg(feature = "postgres")]
            Conn::Postgres(c) => c.batch_execute(sql).map_err(|e| e.to_string()),
        }
    }
}

/// `$1` placeholders as SQLite's numbered `?1` (which bind by their number, where SQLite's
/// `$NAME` would bind by the order of first use).
fn sqlite_sql(sql: &str) -> String {
    let mut out = String::with_capacity(sql.len());
    let mut chars = sql.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '$' && chars.peek().is_some_and(|d| d.is_ascii_digit()) {
            out.push('?');
        } else {
            out.push(c);
        }
    }
    out
}

fn sqlite_arg<'a>(a: &'a Arg<'a>) -> rusqlite::types::ToSqlOutput<'a> {
    use rusqlite::types::{ToSqlOutput, Value, ValueRef};
    match *a {
        Arg::F(v) => ToSqlOutput::Owned(Value::Real(v)),
        Arg::I(v) => ToSqlOutput::Owned(Value::Integer(v)),
        Arg::T(s) => ToSqlOutput::Borrowed(ValueRef::Text(s.as_bytes())),
        Arg::OptT(Some(s)) => ToSqlOutput::Borrowed(ValueRef::Text(s.as_bytes())),
        Arg::OptT(None) => ToSqlOutput::Owned(Value::Null),
        Arg::B(b) => ToSqlOutput::Owned(Value::Integer(b as i64)),
    }
}

#[cfg(feature = "postgres")]
fn pg_args(args: &[Arg]) -> Vec<Box<dyn postgres::types::ToSql + Sync>> {
    args.iter()
        .map(|a| -> Box<dyn postgres::types::ToSql + Sync> {
            match *a {
                Arg::F(v) => Box::new(v),
                Arg::I(v) => Box::new(v),
                Arg::T(s) => Box::new(s.to_string()),
                Arg::OptT(s) => Box::new(s.map(str::to_string)),
                Arg::B(b) => Box::new(b),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placeholders_become_sqlite_numbered_ones() {
        assert_eq!(sqlite_sql("VALUES ($1, $2, 'a$b', $10)"), "VALUES (?1, ?2, 'a$b', ?10)");
    }

    #[test]
    fn a_url_is_named_without_its_password() {
        let t = Target::parse("postgres://line:secret@db.example:5432/coilscope");
        assert_eq!(t.name(), "postgres://line:***@db.example:5432/coilscope");
        assert_eq!(Target::parse("postgresql://line@db/x").name(), "postgresql://line@db/x");
    }
}
