/* Codes the host writes into the kernels' parameters and reads back from their tallies, named
 * once for both sides: clppm/compute/constants.py holds the same names and values, and
 * tests/test_constants.py checks the two against each other. */
#ifndef CLPPM_CONSTANTS_H
#define CLPPM_CONSTANTS_H

/* light source kinds: Params.src_kind, EyeParams.light_kind */
#define SRC_PENCIL 0                    /* a collimated pencil beam at the light's centre */
#define SRC_WIDE 1                      /* a collimated beam of the light's full width */
#define SRC_POINT 2                     /* an isotropic point light */

/* photon storage rules: Params.store_rule */
#define STORE_RULE_ALL 0                /* every scattering event (the paper's) */
#define STORE_RULE_IMPORTANCE 1         /* importance-driven, weight 1/probability */

/* the eye pass's modes: eye_pass's argument `write` */
#define EYE_COUNT 0                     /* count each ray's sample points and pieces */
#define EYE_STORE 1                     /* store them at the counts' prefix sums */
#define EYE_STORE_GEOMETRY 2            /* and each piece's geometry (the beam estimator) */

/* the photon pass's tallies per band: categories, then one absorption tally per layer */
#define TALLY_SPECULAR 0                /* reflected at the surface */
#define TALLY_DIFFUSE 1                 /* left through the surface after scattering */
#define TALLY_TRANSMITTED 2             /* left through the bottom */
#define TALLY_LOST 3                    /* left through the sides */
#define TALLY_RR_GAIN 4                 /* Russian roulette: the survivors' added weight */
#define TALLY_RR_LOSS 5                 /* Russian roulette: the ended paths' weight */
#define TALLY_MISSED 6                  /* emitted but never reached the volume */
#define TALLY_DIFFUSE_CONE 7            /* the part of TALLY_DIFFUSE within the reflectance cone */
#define TALLY_ABSORBED0 8               /* absorbed in layer 0; layer L at TALLY_ABSORBED0 + L */

#endif
