"""Foundation: the `Status` enumeration and which JAX transformations a call is made under."""
