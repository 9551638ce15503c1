/* Work shared by the devices of one launch (nrpose/device/mailbox.py Jobs,
 * nrpose/device/launch.py launch_shared):
 * the same kernel runs at once on PoCL's worker threads and on the calling
 * thread, and each work-item takes the next block of work until none are left.
 * Blocks are handed out in order, so a work-item that starts late finds fewer
 * or none. Which work-item takes a block does not change its result.
 *
 * The host publishes each launch (a "job") in `jobs`, a fine-grained SVM int
 * array with atomics shared by the devices (an ordinary buffer when only the
 * calling thread runs the kernel):
 *   jobs[JOB_NEXT]    tag << JOB_TAG_SHIFT | next block to take; the tag (11 bits)
 *                     changes with every job (1..2047, cycling), so that a
 *                     work-item still holding an earlier job's tag cannot take a
 *                     block of the next one (not guarded: a work-item held up between
 *                     reading the counter and its compare-and-swap for exactly a
 *                     multiple of 2047 jobs, which then see the same counter value)
 *   JOB_BLOCKS_OF(jobs, tag), JOB_FRAMES_OF(jobs, tag), JOB_ENDS_OF(jobs, tag)
 *                     the job's blocks and frames (frames read again after each block
 *                     is taken: a standing work-item serves jobs of different batch
 *                     sizes) and whether it is taken from both ends, in one of two
 *                     descriptors (JOB_DESC), by the tag's parity
 *   A job taken from both ends (at most 1,000 blocks, nrpose/device/mailbox.py JOB_ENDS_MAX_BLOCKS,
 *   so that no count of both ends reads as JOB_PROLOGUE or JOB_IN_PROLOGUE) counts in the block
 *   field the blocks taken from its start (the low JOB_END_BITS bits), which standing
 *   workers take, and from its end (the next JOB_END_BITS), which work-items of role
 *   ROLE_CALLER take (the calling thread, and woken workers, which run with that role):
 *   with a standing worker the two cores then pose about the same points in every launch, and the bound
 *   data of a job that fits in their two L2 caches, not in one, stays where it is read
 *   (the box's point rig, 588 KB: standing spans 1.02-1.42x; on rigs of 2 MB and more
 *   0.92-0.99x, so owners ask for it by size: nrpose/device/mailbox.py ENDS_MAX_BOUND_BYTES).
 *   jobs[JOB_DONE]    blocks finished: each work-item adds its count once, after its
 *                     blocks' writes (a cache line of its own: the block counter's
 *                     line already moves between the cores at every block taken)
 *   jobs[JOB_QUIT]    set by the host: a standing work-item returns
 *   jobs[JOB_STANDING] set by the host when it enqueues a standing work-item, cleared
 *                     by the work-item when it returns
 * The host publishes a job with one write: it first fills the descriptor of the new
 * tag's parity and zeroes JOB_DONE (the last job is done: the host waited for it, and
 * its work-items have counted; a work-item still holding the last tag reads the other
 * descriptor, whose blocks are all taken, and one holding an older tag fails its
 * compare-and-swap), then writes JOB_NEXT = the new tag with block 0 (open), or with
 * JOB_PROLOGUE: the job has a prologue (per-job work that every block needs, e.g. the
 * pose kernel's rotation tables), which the first work-item to arrive claims
 * (JOB_IN_PROLOGUE), runs and then opens the job at block 0; the others wait to take
 * blocks until it is open. Whoever runs it, a standing worker usually does, while the
 * calling thread is still entering its kernel. (Closing the counter first, then writing
 * the counts and opening it, had put four writes to the line a standing worker polls
 * between the publication and the open: the box's segment pose, standing spans
 * 1.03-1.06x, per round.)
 *
 * `role`, the kernel's last argument, says what a work-item does:
 *   ROLE_CALLER (0)  takes blocks of the published job, then waits until every block
 *                    is done (some perhaps by other work-items), so that the host's
 *                    wait on the calling thread's queue is the wait for the whole job
 *   n > 0            a standing worker: takes blocks of the published job, then
 *                    polls `jobs` for the next one and serves it too, until n polls
 *                    in a row find none or the host sets JOB_QUIT; a pose then costs
 *                    no wake-up of PoCL's worker thread (13-19 us of the calling
 *                    thread's time, and the worker started 20-40 us late).
 * (The host sets role 0 once, with the other arguments, and gives a standing worker a
 * clone of the kernel: pyopencl's set_arg of an int takes ~15 us, too much per pose.)
 *
 * Usage, with `jobs` and `role` the kernel's last two arguments, blocks of `block` items
 * (chunks, groups) out of `count`:
 *     FOR_EACH_ITEM(g, F, jobs, role, block, count) {
 *         ... item g, for the F frames of its job ...
 *     }
 * (FOR_EACH_JOB and FOR_EACH_ITEM_OF_JOB, below, are its parts.) With a prologue:
 *     FOR_EACH_JOB(jobs, role) {
 *         if (claim_prologue(jobs, job_tag_)) {
 *             ... the job's prologue, for its JOB_FRAMES_OF(jobs, job_tag_) frames ...
 *             open_job(jobs, job_tag_);
 *         }
 *         FOR_EACH_ITEM_OF_JOB(g, F, jobs, block, count) { ... }
 *     }
 * or, to handle a block's items as a whole (kernels/nrmls.cl: its frames' pointers found
 * once per block), FOR_EACH_BLOCK(b, jobs) { ... block b, items b * block .., of the job's
 * JOB_FRAMES_OF(jobs, job_tag_) frames (read after the block is taken) ... } in place of the last.
 *
 * What orders a block's reads after the prologue's writes, and the host's after the
 * blocks': OpenCL 1.2 makes global memory consistent between work-items only at a
 * barrier of their work-group, and promises nothing between work-groups of a kernel, nor
 * between devices (its section 3.3.1); its atomic_* functions are atomic, and order
 * nothing else. Nor does it promise that work-groups run at the same time, which the
 * calling thread's wait for the others' blocks (and the others' wait for the prologue)
 * needs. So this protocol is outside the 1.2 model, and the host uses it only where the
 * implementation gives both: PoCL's CPU devices on x86 (nrpose/device/policy.py
 * standing_workers_possible), where every work-group runs on a thread of the process,
 * x86's total store order keeps a core's stores in order and its loads in order (and a
 * locked compare-and-swap is a full barrier), and JOB_RELEASE / JOB_ACQUIRE keep the
 * compiler from moving a block's memory accesses across the mailbox's. (In the C11 terms
 * of OpenCL 2.0, the kernel's side is fence synchronisation, a release fence before the
 * atomic that opens a job or counts blocks done, an acquire fence after the atomic that
 * takes a block or the read that sees the count, but for the polls, which are volatile
 * loads rather than atomic ones: on x86, one aligned load either way. The host's side,
 * numpy stores to shared memory, has only x86's order.)
 *
 * Everywhere else the host builds with -DPLAIN_OPENCL, and a launch is plain OpenCL
 * 1.2: the kernel only reads the mailbox (the job's descriptor, written before the
 * launch), work-item i takes blocks i, i + n, ... (n work-items; the ends, JOB_DONE and
 * roles other than these two unused), and a job's prologue is a launch of its own before
 * the blocks', in the same in-order queue, with role ROLE_PROLOGUE (its work-item 0 runs
 * it, FOR_EACH_BLOCK gives it no block), so that the queue orders the prologue's writes
 * before the blocks' reads, and the host's wait for the queue orders the blocks' writes
 * before its reads.
 */
#define JOB_NEXT 0
#define JOB_QUIT 3
#define JOB_STANDING 4
#define JOB_DESC 8        /* two descriptors (blocks, frames, ends, -), by the tag's parity */
#define JOB_DESC_INTS 4
#define JOB_BLOCKS_OF(jobs, tag) (jobs)[JOB_DESC + JOB_DESC_INTS * ((tag) & 1)]
#define JOB_FRAMES_OF(jobs, tag) (jobs)[JOB_DESC + JOB_DESC_INTS * ((tag) & 1) + 1]
#define JOB_ENDS_OF(jobs, tag) (jobs)[JOB_DESC + JOB_DESC_INTS * ((tag) & 1) + 2]
#define JOB_END_BITS 10
#define JOB_END_MASK ((1 << JOB_END_BITS) - 1)
#define JOB_DONE 16       /* 64 bytes on (the mailbox is 128-byte aligned, 32 ints) */
#define JOB_TAG_SHIFT 20
#define JOB_BLOCK_MASK ((1 << JOB_TAG_SHIFT) - 1)
#define JOB_PROLOGUE (JOB_BLOCK_MASK - 1)        /* published; its prologue not yet claimed */
#define JOB_IN_PROLOGUE (JOB_BLOCK_MASK - 2)     /* a work-item runs the prologue */
#define ROLE_CALLER 0
#define ROLE_PROLOGUE (-1)    /* PLAIN_OPENCL: the launch of the job's prologue */

#ifdef PLAIN_OPENCL
/* The job published when the launch was enqueued (its tag: the descriptor's parity),
 * served once by each work-item. */
#define FOR_EACH_JOB(jobs, role) \
    for (int job_tag_ = (jobs)[JOB_NEXT] >> JOB_TAG_SHIFT, job_role_ = (role), job_once_ = 1; job_once_; job_once_ = 0)

/* The prologue's launch runs it (its work-item 0). */
#define claim_prologue(jobs, tag) (job_role_ == ROLE_PROLOGUE && get_global_id(0) == 0)
#define open_job(jobs, tag) ((void)0)

/* Blocks i, i + n, ... of the job for work-item i of n; none for the prologue's launch. */
#define FOR_EACH_BLOCK(b, jobs) \
    for (int b = job_role_ == ROLE_PROLOGUE ? JOB_BLOCKS_OF(jobs, job_tag_) : (int)get_global_id(0); \
         b < JOB_BLOCKS_OF(jobs, job_tag_); b += (int)get_global_size(0))
#else
/* a spin-wait hint to the core (x86: pause; it spares the sibling hyperthread) */
#if defined(__x86_64__) || defined(__i386__)
#define SPIN_PAUSE() __builtin_ia32_pause()
#else
#define SPIN_PAUSE() ((void)0)
#endif

/* Ordering of a block's reads and writes against the mailbox, for the compiler (the
 * hardware's is x86's, where the host enables standing workers: nrpose/device/policy.py
 * standing_workers_possible): OpenCL 1.x atomics promise none, PoCL's mem_fence
 * compiles to nothing, clang's fences are compiler barriers here (release, acquire). */
#if defined(__clang__)
#define JOB_RELEASE() __atomic_thread_fence(__ATOMIC_RELEASE)
#define JOB_ACQUIRE() __atomic_thread_fence(__ATOMIC_ACQUIRE)
#else
#define JOB_RELEASE() mem_fence(CLK_GLOBAL_MEM_FENCE)
#define JOB_ACQUIRE() mem_fence(CLK_GLOBAL_MEM_FENCE)
#endif

/* The next block of the job tagged `tag`, taken by a work-item of `role` (from the job's
 * end by the calling thread where the job is taken from both ends); -1 when the job has
 * none left (or is no longer the published one). Waits while the job's prologue runs.
 * The block's reads come after the taking (and so after the prologue's writes). */
static inline int take_block(volatile __global int *jobs, const int tag, const int role)
{
    for (;;) {
        const int v = jobs[JOB_NEXT];
        if ((v >> JOB_TAG_SHIFT) != tag)
            return -1;
        const int b = v & JOB_BLOCK_MASK, n = JOB_BLOCKS_OF(jobs, tag);
        if (b == JOB_IN_PROLOGUE || b == JOB_PROLOGUE) {
            SPIN_PAUSE();
            continue;
        }
        int block = b, step = 1;
        if (JOB_ENDS_OF(jobs, tag)) {
            const int front = b & JOB_END_MASK, back = b >> JOB_END_BITS;
            if (front + back >= n)
                return -1;
            if (role == ROLE_CALLER) {
                block = n - 1 - back;
                step = 1 << JOB_END_BITS;
            } else {
                block = front;
            }
        } else if (b >= n) {
            return -1;
        }
        if (atomic_cmpxchg(jobs + JOB_NEXT, v, v + step) == v) {
            JOB_ACQUIRE();
            return block;
        }
    }
}

/* Whether the job whose counter reads `v` has blocks left, or its prologue to run or running. */
static inline int job_open(volatile __global int *jobs, const int v)
{
    const int tag = v >> JOB_TAG_SHIFT, b = v & JOB_BLOCK_MASK;
    if (b == JOB_PROLOGUE || b == JOB_IN_PROLOGUE)
        return 1;
    return (JOB_ENDS_OF(jobs, tag) ? (b & JOB_END_MASK) + (b >> JOB_END_BITS) : b) < JOB_BLOCKS_OF(jobs, tag);
}

/* Whether to serve a job (again): sets *tag to the job's. ROLE_CALLER serves the
 * published job once, then waits for the blocks others took; a standing worker serves
 * each newly published job that has blocks left or its prologue still to run (or
 * running), and returns 0 after `role` idle polls
 * or on JOB_QUIT. *served: whether the caller has served its job. */
static inline int next_job(volatile __global int *jobs, const int role, int *tag, int *served)
{
    if (role == ROLE_CALLER) {
        if (*served) {
            while (jobs[JOB_DONE] < JOB_BLOCKS_OF(jobs, *tag))
                SPIN_PAUSE();
            JOB_ACQUIRE();      /* the others' blocks are written */
            return 0;
        }
        *tag = jobs[JOB_NEXT] >> JOB_TAG_SHIFT;
        *served = 1;
        return 1;
    }
    for (int idle = 0; idle < role && !jobs[JOB_QUIT]; ++idle) {
        const int v = jobs[JOB_NEXT];
        if ((v >> JOB_TAG_SHIFT) != *tag && job_open(jobs, v)) {
            *tag = v >> JOB_TAG_SHIFT;
            return 1;
        }
        SPIN_PAUSE();
    }
    atomic_xchg(jobs + JOB_STANDING, 0);
    return 0;
}

/* Whether this work-item claims the prologue of the job tagged `tag` (it then runs it
 * and calls open_job); 0 when the job has none or another work-item claimed it. */
static inline int claim_prologue(volatile __global int *jobs, const int tag)
{
    const int v = tag << JOB_TAG_SHIFT | JOB_PROLOGUE;
    if (jobs[JOB_NEXT] != v || atomic_cmpxchg(jobs + JOB_NEXT, v, tag << JOB_TAG_SHIFT | JOB_IN_PROLOGUE) != v)
        return 0;
    JOB_ACQUIRE();      /* the prologue's reads (e.g. the job's frames) after the claim */
    return 1;
}

/* Opens the job tagged `tag` at block 0, after its prologue's writes. */
static inline void open_job(volatile __global int *jobs, const int tag)
{
    JOB_RELEASE();
    atomic_xchg(jobs + JOB_NEXT, tag << JOB_TAG_SHIFT);
}

#define FOR_EACH_JOB(jobs, role) \
    for (int job_tag_ = -1, job_served_ = 0, job_role_ = (role); next_job((jobs), (role), &job_tag_, &job_served_); )

/* Adds a work-item's `taken` blocks of a job to JOB_DONE, after their writes; 0. */
static inline int count_done(volatile __global int *jobs, const int taken)
{
    if (taken) {
        JOB_RELEASE();
        atomic_add(jobs + JOB_DONE, taken);
    }
    return 0;
}

/* the blocks are counted done once, when none are left to take (the condition's
 * second operand runs then): a `break` or `return` inside the loop would skip the count
 * and leave the calling thread waiting for ever */
#define FOR_EACH_BLOCK(b, jobs) \
    for (int b = take_block((jobs), job_tag_, job_role_), taken_ = 0; b >= 0 || count_done((jobs), taken_); \
         b = (++taken_, take_block((jobs), job_tag_, job_role_)))

#endif

/* Item g of every block of the job being served (inside FOR_EACH_JOB), with F the
 * frames of the block's job (read once per block, after it is taken). */
#define FOR_EACH_ITEM_OF_JOB(g, F, jobs, block, count)                                    \
    FOR_EACH_BLOCK(b_, jobs)                                                              \
    for (int g = b_ * (block), g_end_ = (b_ + 1) * (block) < (count) ? (b_ + 1) * (block) : (count), \
         F = JOB_FRAMES_OF(jobs, job_tag_); g < g_end_; ++g)

/* Item g of every block of every job the work-item serves (jobs without a prologue). */
#define FOR_EACH_ITEM(g, F, jobs, role, block, count)                                     \
    FOR_EACH_JOB(jobs, role) FOR_EACH_ITEM_OF_JOB(g, F, jobs, block, count)
