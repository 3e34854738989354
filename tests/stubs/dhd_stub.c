/* A stand-in for Force Dimension's libdhd.so, compiled by tests/test_devices.py: the DHD calls
   rtfem's adapter makes (dhdc.h's names and signatures: metres, newtons, 0 on success and -1 on an
   error with its number and text), a scripted handle (one position per dhdGetPosition call, held
   at the last), the forces written recorded per call, and an error injected at a chosen call.
   Not the SDK: a test double. */
#include <string.h>

#define MAXN 100000
static double traj[MAXN][3];
static int btns[MAXN];
static double forces[MAXN][3];
static int n_script = 0;
static volatile int calls = 0;     /* dhdGetPosition calls */
static volatile int n_forces = 0;  /* dhdSetForce calls */
static int fail_at = -1, fail_code = 0, no_device = 0, force_enabled = 0, is_open = 0;
static double max_force = 12.0;
static int last_error = 0;
static char last_text[128] = "no error";

static void set_error(int code, const char *text) { last_error = code; strncpy(last_text, text, 127); }
static int now(void) { int k = calls; return k < n_script ? k : (n_script > 0 ? n_script - 1 : 0); }

int dhdOpen(void) {
    if (no_device) { set_error(5, "no device found"); return -1; }
    is_open = 1;
    return 0;
}
int dhdClose(char id) { (void)id; is_open = 0; return 0; }
int dhdEnableForce(unsigned char on, char id) { (void)id; force_enabled = on; return 0; }
double dhdGetMaxForce(char id) { (void)id; return max_force; }
int dhdGetPosition(double *px, double *py, double *pz, char id) {
    (void)id;
    if (fail_at >= 0 && calls >= fail_at) {
        set_error(fail_code, fail_code == 2 ? "communication error between the host and the device" : "undefined error");
        return -1;
    }
    int k = now();
    *px = traj[k][0]; *py = traj[k][1]; *pz = traj[k][2];
    calls = calls + 1;
    return 0;
}
int dhdGetButton(int index, char id) { (void)id; return (btns[now()] >> index) & 1; }
int dhdSetForce(double fx, double fy, double fz, char id) {
    (void)id;
    int k = n_forces;
    if (k < MAXN) { forces[k][0] = fx; forces[k][1] = fy; forces[k][2] = fz; }
    n_forces = k + 1;
    return 0;
}
int dhdErrorGetLast(void) { return last_error; }
const char *dhdErrorGetLastStr(void) { return last_text; }

/* the test's controls */
void stub_script(const double *xyz, const int *buttons, int n) {
    if (n > MAXN) n = MAXN;
    for (int i = 0; i < n; i++) {
        traj[i][0] = xyz[3 * i]; traj[i][1] = xyz[3 * i + 1]; traj[i][2] = xyz[3 * i + 2];
        btns[i] = buttons ? buttons[i] : 0;
    }
    n_script = n; calls = 0; n_forces = 0;
}
int stub_frame(void) { return n_forces; }
void stub_forces(double *out, int n) { if (n > MAXN) n = MAXN; memcpy(out, forces, sizeof(double) * 3 * n); }
void stub_fail(int at, unsigned int code) { fail_at = at; fail_code = (int)code; }
void stub_no_device(int on) { no_device = on; }
void stub_max_force(double f) { max_force = f; }
int stub_state(void) { return is_open + 2 * force_enabled; }
void stub_reset(void) { fail_at = -1; no_device = 0; last_error = 0; max_force = 12.0; n_script = 0; calls = 0; n_forces = 0; }
