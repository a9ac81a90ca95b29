import time
from test_storage import telemetry_row, estimate_row, T0_MS
from roadgrip.cloud.storage import open_storage

def batches(n_batches, size=1000, vehicles=10):
    per = size // vehicles
    out = []
    for b in range(n_batches):
        tel, est = [], []
        for v in range(vehicles):
            for i in range(per):
                t = T0_MS + 100 * (b * per + i)
                tel.append(telemetry_row(f"car-{v}", t, speed_mps=20.0 + i * 0.01))
                est.append(estimate_row(f"car-{v}", t))
        out.append((tel, est))
    return out

def run(url, label):
    data = batches(60)
    s = open_storage(url)
    for with_est in (False, True):
        s.close(); s = open_storage(url)
        t = time.perf_counter(); n = 0
        for k, (tel, est) in enumerate(data[:30] if not with_est else data[30:]):
            n += s.write_batch(tel, est if with_est else [])[0]
        dt = time.perf_counter() - t
        print(f"BENCH {label} {'tel+est' if with_est else 'tel only'}: {n} rows in {dt:.2f}s = {n/dt:,.0f} telemetry rows/s")
    # duplicate batch
    t = time.perf_counter()
    for tel, est in data[:10]:
        s.write_batch(tel, [])
    dt = time.perf_counter() - t
    print(f"BENCH {label} duplicates: {10000/dt:,.0f} rows/s")
    s.close()

def test_bench_sqlite(tmp_path):
    run(f"sqlite:///{tmp_path}/b.db", "sqlite")

def test_bench_pg(postgres_database_url):
    run(postgres_database_url, "postgresql")
