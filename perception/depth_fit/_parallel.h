/* The depth fit's kernels' rows shared out over threads: a batch's rows are independent fits, taken in chunks by
   an OpenMP team, so each row's result is the same on any number of threads. The team is torch's own (the kernels
   load after torch, whose libgomp they share): its threads, spinning between torch's ops, take a chunk at once. */

#ifndef POSEGRASP_PARALLEL_H
#define POSEGRASP_PARALLEL_H

#include <stdint.h>

/* Work on rows [begin, end) of a batch: returns 0, or a kernel's error status. */
typedef int (*posegrasp_rows)(void *work, int64_t begin, int64_t end);

/* ``run`` on all ``rows`` of a batch, in chunks of about a quarter of a thread's share, on up to ``threads``
   threads. Returns 0 or the status of a chunk that failed. */
static int posegrasp_parallel(posegrasp_rows run, void *work, int64_t rows, int64_t threads) {
    threads = rows < threads ? rows : (threads < 1 ? 1 : threads);
    int64_t chunk = rows / (4 * threads) > 1 ? rows / (4 * threads) : 1, chunks = (rows + chunk - 1) / chunk;
    int status = 0;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads) if (threads > 1)
    for (int64_t c = 0; c < chunks; c++) {
        int done = run(work, c * chunk, (c + 1) * chunk < rows ? (c + 1) * chunk : rows);
        if (done != 0) {
#pragma omp atomic write
            status = done;
        }
    }
    return status;
}

#endif
