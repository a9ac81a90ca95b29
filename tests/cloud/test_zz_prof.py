import time
import psycopg
import sqlalchemy as sa
from sqlalchemy.engine import make_url
from test_zz_bench import batches
from roadgrip.cloud import storage as st
from roadgrip.data.schema import TELEMETRY_COLUMNS as COLS

def test_raw(postgres_database_url):
    data = batches(12)
    s = st.open_storage(postgres_database_url); s.close()
    ci = make_url(postgres_database_url).set(drivername="postgresql").render_as_string(False)
    cols = ", ".join(COLS)
    with psycopg.connect(ci) as conn:
        def timeit(label, fn):
            conn.execute("TRUNCATE telemetry"); conn.commit()
            t = time.perf_counter()
            for tel, _ in data[1:]:
                fn(tel); conn.commit()
            print(f"RAW {label}: {11000/(time.perf_counter()-t):,.0f} rows/s")
        ph = ", ".join(["%s"] * len(COLS))
        def em(tel):
            with conn.cursor() as cur:
                cur.executemany(f"INSERT INTO telemetry ({cols}) VALUES ({ph}) ON CONFLICT DO NOTHING", [tuple(r[c] for c in COLS) for r in tel])
        timeit("executemany tuples", em)
        types = ["text", "bigint"] + ["float8"] * 9 + ["float8"]*2 + ["bool", "bool", "float8"]
        types = {c.name: {"string": "text", "int64": "bigint", "double": "float8", "bool": "bool"}[str(c.type)] for c in st.TELEMETRY}
        un = ", ".join(f"%s::{types[c]}[]" for c in COLS)
        def unnest(tel):
            cur = conn.execute(f"INSERT INTO telemetry ({cols}) SELECT * FROM unnest({un}) ON CONFLICT DO NOTHING RETURNING timestamp_ms", [[r[c] for r in tel] for c in COLS])
            cur.fetchall()
        timeit("unnest", unnest)
        def copy(tel):
            with conn.cursor() as cur, cur.copy(f"COPY telemetry ({cols}) FROM STDIN") as cp:
                for r in tel: cp.write_row(tuple(r[c] for c in COLS))
        timeit("copy", copy)
