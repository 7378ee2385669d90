/* The pinhole camera shared by the eye pass (eye.cl) and the path tracer (pt.cl): one struct,
 * one ray generation.  Host side: clppm/scene/camera.py (CAMERA_DTYPE, Camera.struct). */
#ifndef CLPPM_CAMERA_H
#define CLPPM_CAMERA_H

typedef struct {
    float cpx, cpy, cpz;        /* position (um) */
    float fx, fy, fz;           /* forward, right, up: an orthonormal frame */
    float rx, ry, rz;
    float ux, uy, uz;
    float tan_half, aspect;     /* tan(vertical fov / 2), width / height */
    int width, height;
} Camera;

/* Both return a float4 (w = 0), not a float3: Intel's CPU compiler gives a 3-vector returned
 * by a function it keeps as a call the right value in the first vectorised lane only
 * (docs/devices.md). */
inline float4 camera_pos(__constant const Camera* c) {
    return (float4)(c->cpx, c->cpy, c->cpz, 0.0f);
}

/* Unit direction of the ray through image point (u, v), in pixels from the top-left corner
 * (clppm/scene/camera.py Camera.ray). */
inline float4 camera_dir(__constant const Camera* c, float u, float v) {
    const float sx = (2.0f * u / (float)c->width - 1.0f) * c->tan_half * c->aspect;
    const float sy = (1.0f - 2.0f * v / (float)c->height) * c->tan_half;
    const float3 fwd = (float3)(c->fx, c->fy, c->fz), right = (float3)(c->rx, c->ry, c->rz);
    const float3 up = (float3)(c->ux, c->uy, c->uz);
    return (float4)(normalize(fwd + sx * right + sy * up), 0.0f);
}

#endif
