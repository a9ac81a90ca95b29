import time
import psycopg
from sqlalchemy.engine import make_url
from test_zz_bench import batches
from roadgrip.cloud import storage as st
from roadgrip.data.schema import TELEMETRY_COLUMNS as COLS

def test_raw(postgres_database_url):
    data = batches(22)
    s = st.open_storage(postgres_database_url); s.close()
    ci = make_url(postgres_database_url).set(drivername="postgresql").render_as_string(False)
    cols = ", ".join(COLS)
    types = {c.name: {"string": "text", "int64": "bigint", "double": "float8", "bool": "bool"}[str(c.type)] for c in st.TELEMETRY}
    with psycopg.connect(ci) as conn:
        def timeit(label, fn, cursor_factory=None):
            conn.execute("TRUNCATE telemetry"); conn.commit()
            for tel, _ in data[:2]:
                fn(tel); conn.commit()
            t = time.perf_counter(); c = time.process_time()
            for tel, _ in data[2:]:
                fn(tel); conn.commit()
            w = time.perf_counter() - t
            print(f"RAW {label}: {20000/w:,.0f} rows/s, client cpu {100*(time.process_time()-c)/w:.0f}%")
        n = len(COLS)
        raw_sql = f"INSERT INTO telemetry ({cols}) VALUES " + ", ".join("(" + ", ".join(f"${i*n+j+1}" for j in range(n)) + ")" for i in range(1000)) + " ON CONFLICT DO NOTHING RETURNING timestamp_ms"
        def multivalues(tel):
            with psycopg.RawCursor(conn) as cur:
                cur.execute(raw_sql, [r[c] for r in tel for c in COLS]); cur.fetchall()
        timeit("multi-values rawcursor", multivalues)
        un = ", ".join(f"%s::{types[c]}[]" for c in COLS)
        for binary in (False, True):
            def unnest(tel):
                conn.execute(f"INSERT INTO telemetry ({cols}) SELECT * FROM unnest({un}) ON CONFLICT DO NOTHING RETURNING timestamp_ms", [[r[c] for r in tel] for c in COLS], binary=binary).fetchall()
            timeit(f"unnest binary={binary}", unnest)
        ph = ", ".join(["%s"] * n)
        def em(tel):
            with conn.cursor() as cur:
                cur.executemany(f"INSERT INTO telemetry ({cols}) VALUES ({ph}) ON CONFLICT DO NOTHING", [tuple(r[c] for c in COLS) for r in tel])
        timeit("executemany", em)
