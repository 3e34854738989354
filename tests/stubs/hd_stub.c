/* A stand-in for OpenHaptics' libHD.so, compiled by tests/test_devices.py: the HD API functions
   rtfem's adapter calls (names, constants and signatures of the SDK's hdDefines.h 3.00,
   hdScheduler.h, hdDevice.h), a scheduler thread at 1 kHz, a scripted stylus (positions in mm
   and buttons per servo frame), the forces the adapter writes recorded per frame, and errors or
   a disconnection injected at a chosen frame; whether force output is enabled (hdEnable / hdDisable
   of HD_FORCE_OUTPUT) and whether the servo callback is still scheduled. Not the SDK: a test double. */
#include <pthread.h>
#include <string.h>
#include <time.h>

typedef unsigned int HHD;
typedef struct { unsigned int errorCode; int internalErrorCode; unsigned int hHD; } HDErrorInfo;
typedef unsigned int (*HDSchedulerCallback)(void *);

#define MAXN 100000
static double traj[MAXN][3];
static int btns[MAXN];
static double forces[MAXN][3];
static int n_script = 0;
static volatile int frame = 0;
static unsigned int errs[64];
static int n_err = 0;
static int fail_frame = -1, disconnect_frame = -1;
static unsigned int fail_code = 0;
static double nominal_max_force = 3.3;                     /* N */
static double usable[6] = {-80, -60, -35, 80, 60, 35};     /* mm */
static double cur_force[3];
static volatile int force_output = 0;
static HDSchedulerCallback callback = 0;
static void *callback_data = 0;
static pthread_t thread;
static volatile int running = 0;
static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;

static void push_error(unsigned int code) {
    pthread_mutex_lock(&lock);
    if (n_err < 64) errs[n_err++] = code;
    pthread_mutex_unlock(&lock);
}

static int now(void) { int k = frame; return k < n_script ? k : (n_script > 0 ? n_script - 1 : 0); }

HHD hdInitDevice(const char *name) {
    if (name && strcmp(name, "missing") == 0) { push_error(0x0302); return 0xFFFFFFFFu; }
    return 1;
}
void hdDisableDevice(HHD h) { (void)h; }
void hdMakeCurrentDevice(HHD h) { (void)h; }
void hdBeginFrame(HHD h) {
    (void)h;
    if (disconnect_frame >= 0 && frame >= disconnect_frame) push_error(0x0302);
}
void hdEndFrame(HHD h) {
    (void)h;
    int k = frame;
    if (k < MAXN) { forces[k][0] = cur_force[0]; forces[k][1] = cur_force[1]; forces[k][2] = cur_force[2]; }
    if (k == fail_frame) push_error(fail_code);
    frame = k + 1;
}
HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {0, 0, 1};
    pthread_mutex_lock(&lock);
    if (n_err > 0) e.errorCode = errs[--n_err];
    pthread_mutex_unlock(&lock);
    return e;
}
const char *hdGetErrorString(unsigned int code) { (void)code; return "stub"; }
void hdEnable(unsigned int cap) { if (cap == 0x4000) force_output = 1; }
void hdDisable(unsigned int cap) { if (cap == 0x4000) force_output = 0; }
void hdGetDoublev(unsigned int p, double *v) {
    int k = now();
    if (p == 0x2050) { v[0] = traj[k][0]; v[1] = traj[k][1]; v[2] = traj[k][2]; }
    else if (p == 0x2603) v[0] = nominal_max_force;
    else if (p == 0x2551) memcpy(v, usable, sizeof usable);
    else push_error(0x0100);
}
void hdGetIntegerv(unsigned int p, int *v) {
    if (p == 0x2000) v[0] = btns[now()]; else push_error(0x0100);
}
void hdSetDoublev(unsigned int p, const double *v) {
    if (p == 0x2700) { cur_force[0] = v[0]; cur_force[1] = v[1]; cur_force[2] = v[2]; } else push_error(0x0100);
}
static void *scheduler(void *arg) {
    (void)arg;
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    while (running) {
        HDSchedulerCallback cb = callback;
        if (cb && cb(callback_data) == 0) callback = 0;
        t.tv_nsec += 1000000;
        if (t.tv_nsec >= 1000000000) { t.tv_nsec -= 1000000000; t.tv_sec += 1; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &t, 0);
    }
    return 0;
}
void hdStartScheduler(void) { if (!running) { running = 1; pthread_create(&thread, 0, scheduler, 0); } }
void hdStopScheduler(void) { if (running) { running = 0; pthread_join(thread, 0); } }
unsigned long hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, unsigned short priority) {
    (void)priority; callback_data = data; callback = cb; return 1;
}
void hdUnschedule(unsigned long handle) { (void)handle; callback = 0; }

/* the test's controls */
void stub_script(const double *xyz_mm, const int *buttons, int n) {
    if (n > MAXN) n = MAXN;
    for (int i = 0; i < n; i++) {
        traj[i][0] = xyz_mm[3 * i]; traj[i][1] = xyz_mm[3 * i + 1]; traj[i][2] = xyz_mm[3 * i + 2];
        btns[i] = buttons ? buttons[i] : 0;
    }
    n_script = n;
    frame = 0;
}
int stub_frame(void) { return frame; }
void stub_forces(double *out, int n) { if (n > MAXN) n = MAXN; memcpy(out, forces, sizeof(double) * 3 * n); }
void stub_fail(int at, unsigned int code) { fail_frame = at; fail_code = code; }
void stub_disconnect(int at) { disconnect_frame = at; }
int stub_force_output(void) { return force_output; }
int stub_scheduled(void) { return callback != 0; }
void stub_reset(void) { fail_frame = disconnect_frame = -1; n_err = 0; frame = 0; n_script = 0; callback = 0; }
