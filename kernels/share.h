/* Work shared by the devices of one launch (nrpose/device.py launch_shared):
 * the same kernel runs at once on PoCL's worker threads and on the calling
 * thread, and each work-item takes the next block of work from one counter
 * (zeroed by the host before the launch) until none are left. Blocks are
 * handed out in order, so a work-item that starts late finds fewer or none.
 * `next` is a fine-grained SVM int with atomics shared by the devices (or an
 * ordinary buffer when only one device runs the kernel). */
#define FOR_EACH_BLOCK(b, next, nblocks) \
    for (int b = atomic_inc(next); b < (nblocks); b = atomic_inc(next))
