//! A fresh PostgreSQL database per test.

use crate::skip;

/// A fresh PostgreSQL database for test `name`, or `None` after printing why the test is
/// skipped. CANLIFT_TEST_POSTGRES is a URL to an existing database whose user may create
/// databases (CI sets it after starting Debian's PostgreSQL); with CANLIFT_REQUIRE_POSTGRES=1 a
/// missing or unreachable server fails the test instead.
pub async fn postgres(name: &str) -> Option<String> {
    use sqlx::Connection;
    let require = std::env::var("CANLIFT_REQUIRE_POSTGRES").as_deref() == Ok("1");
    let give_up = |reason: String| {
        if require {
            panic!("{reason}");
        }
        skip(&reason);
        None
    };
    let Ok(admin) = std::env::var("CANLIFT_TEST_POSTGRES") else {
        return give_up("postgres: CANLIFT_TEST_POSTGRES is not set".into());
    };
    let mut conn = match sqlx::PgConnection::connect(&admin).await {
        Ok(c) => c,
        Err(e) => return give_up(format!("postgres: {admin}: {e}")),
    };
    let db = format!("canlift_{name}_{}", std::process::id());
    for statement in [
        format!("DROP DATABASE IF EXISTS {db}"),
        format!("CREATE DATABASE {db}"),
    ] {
        if let Err(e) = sqlx::query(&statement).execute(&mut conn).await {
            return give_up(format!("postgres: {statement}: {e}"));
        }
    }
    let base = admin.rsplit_once('/').map_or(admin.as_str(), |(b, _)| b);
    Some(format!("{base}/{db}"))
}
