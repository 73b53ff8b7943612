/* Minimal stand-ins for the libf2c routines used by the f2c translation of RADAU5.
   Printing routines write the Fortran WRITE(6,*) messages to stderr (diagnostics only). */
#include <stdio.h>
#include <math.h>
#include "f2c.h"
integer s_wsle(cilist *a) { (void)a; fputs("[radau5]", stderr); return 0; }
integer e_wsle(void) { fputc('\n', stderr); return 0; }
integer s_wsfe(cilist *a) { (void)a; fputs("[radau5]", stderr); return 0; }
integer e_wsfe(void) { fputc('\n', stderr); return 0; }
integer do_lio(integer *type, integer *number, char *ptr, ftnlen len) {
    integer k;
    for (k = 0; k < *number; k++) {
        switch (*type) {
        case 3: fprintf(stderr, " %d", ((integer *)ptr)[k]); break;          /* TYLONG */
        case 5: fprintf(stderr, " %.6e", ((doublereal *)ptr)[k]); break;     /* TYDREAL */
        case 9: fprintf(stderr, " %.*s", (int)len, ptr); return 0;           /* TYCHAR */
        default: break;
        }
    }
    return 0;
}
integer do_fio(integer *number, char *ptr, ftnlen len) {
    /* formatted output: only used for X (double) in FORMAT 979 */
    if (len == sizeof(doublereal)) fprintf(stderr, " %.6e", *(doublereal *)ptr);
    else if (len == sizeof(integer)) fprintf(stderr, " %d", *(integer *)ptr);
    (void)number;
    return 0;
}
double pow_dd(doublereal *a, doublereal *b) { return pow(*a, *b); }
double pow_di(doublereal *a, integer *n) {
    double x = *a, r = 1.0; integer k = *n;
    if (k == 0) return 1.0;
    if (k < 0) { k = -k; x = 1.0 / x; }
    for (;;) { if (k & 1) r *= x; if (k >>= 1) x *= x; else break; }
    return r;
}
double d_sign(doublereal *a, doublereal *b) { double x = fabs(*a); return (*b >= 0 ? x : -x); }
